r"""Tabulated densities sampled by CDF inversion, and rejection sampling (PBRT 3rd ed. §13.3).

- `Piecewise1D` and `Piecewise2D` are the inversion method of PBRT 3rd ed. §13.3.1
  applied to a density we only know as a table (a histogram, an image, an
  environment map): the CDF of a piecewise-constant density is piecewise
  linear, so it can be tabulated once and inverted exactly by a binary search
  plus a linear interpolation. `Piecewise2D` samples the marginal density of
  the rows, then the conditional density of the column within the row (PBRT's
  `Distribution2D`, §13.6.7 / §14.2.4).
- `rejection` is the rejection method of PBRT 3rd ed. §13.3.2 in fixed shapes, so it
  runs under `jit`: propose in batches, keep what is accepted, stop when `n`
  slots are filled or after `max_rounds` rounds. `disk_rejection` is
  its disk-from-square example, with efficiency $\pi/4$.
"""

from ._distributions import (
    Piecewise1D as Piecewise1D,
    Piecewise2D as Piecewise2D,
    disk_rejection as disk_rejection,
    rejection as rejection,
)


__all__ = ["Piecewise1D", "Piecewise2D", "rejection", "disk_rejection"]
