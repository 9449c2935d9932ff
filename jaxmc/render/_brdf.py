r"""A diffuse base plus a Beckmann microfacet lobe: its evaluation (sampling is `_directions`).

$$ f(\omega_o, \omega_i) = \frac{k_d}{\pi}
   + k_s \frac{D(h)\, G_1(\omega_i) G_1(\omega_o)}{4\cos\theta_i\cos\theta_o},
\qquad D(h) = \frac{e^{-\tan^2\theta_h/\alpha^2}}{\pi\alpha^2\cos^4\theta_h}, $$

with $h$ the half vector, Smith's shadowing for Beckmann (Walter et al. 2007,
rational approximation) and no Fresnel term (a conductor of unit
reflectance, as in Veach's scene). The renderer samples it as a mixture
(`specular_probability`) of `BeckmannLobe` and `CosineHemisphere`.

Everything is written for one shading point and is smooth in $\alpha$, $k_d$
and $k_s$ (with the directions held fixed), so light-sampled images
differentiate cleanly with respect to the material.
"""

from __future__ import annotations

import jax.numpy as jnp

from ._math import dot, normalize, safe_div, safe_sqrt


def _tan2(v, n):
    """$\tan^2\theta$ between unit `v` and `n`, from $|v \times n|^2$ (no cancellation near 0)."""
    c = dot(v, n)
    s2 = dot(jnp.cross(v, n), jnp.cross(v, n))
    return safe_div(s2, c * c)


def beckmann_d(h, n, alpha):
    c = dot(h, n)
    a2 = alpha * alpha
    d = safe_div(jnp.exp(-_tan2(h, n) / a2), jnp.pi * a2 * c**4)
    return jnp.where(c > 0, d, 0.0)


def smith_g1(v, n, alpha):
    tan2 = _tan2(v, n)
    a = safe_div(1.0, alpha * safe_sqrt(tan2))
    a = jnp.where(tan2 > 0, a, 1e3)
    g = (3.535 * a + 2.181 * a * a) / (1.0 + 2.276 * a + 2.577 * a * a)
    return jnp.where(a < 1.6, g, 1.0)


def specular_probability(diffuse, specular):
    total = specular + jnp.mean(diffuse)
    return safe_div(specular, total)


def evaluate(diffuse, specular, alpha, n, wo, wi):
    """BRDF value (RGB) for unit `n`, `wo` (towards the viewer) and `wi` (towards the light)."""
    ci, co = dot(n, wi), dot(n, wo)
    front = (ci > 0) & (co > 0)
    h = normalize(wi + wo)
    glossy = beckmann_d(h, n, alpha) * smith_g1(wi, n, alpha) * smith_g1(wo, n, alpha)
    glossy = safe_div(glossy, 4.0 * ci * co)
    f = diffuse / jnp.pi + specular * glossy
    return jnp.where(front, f, 0.0)
