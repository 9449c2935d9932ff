r"""Statistical checks users can run on their own samplers.

`chi2_test` is Pearson's $\chi^2$ goodness-of-fit test of a sampler against
the density it claims to sample, the way Mitsuba tests its warps and BSDFs
(`mitsuba/python/chi2.py`, `ChiSquareTest`): histogram many samples on a grid
in a 2-D (or 1-D) parameterisation of the domain, integrate the pdf over every
cell numerically to get the expected counts, pool cells whose expected count
is below 5, and compare. A correct sampler gives a uniformly distributed
p-value; a wrong pdf, a missing Jacobian or a biased warp gives $p \approx 0$
once `n` is large enough. Run several such tests with a Bonferroni (or Šidák)
corrected significance level.

!!! Example

    ```python
    import jax, jaxmc

    def sample(key, n):
        return jaxmc.warps.hemisphere_cosine(jax.random.uniform(key, (n, 2)))

    stat, p = jaxmc.testing.chi2_test(
        jax.random.key(0), sample, jaxmc.warps.hemisphere_cosine_pdf,
        "hemisphere", n=100_000, bins=16)
    assert p > 1e-4
    ```
"""

from ._testing._chi2 import Chi2Table as Chi2Table, chi2_table as chi2_table, chi2_test as chi2_test


__all__ = ["chi2_test", "chi2_table", "Chi2Table"]
