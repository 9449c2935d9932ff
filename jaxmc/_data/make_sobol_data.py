"""Regenerate `sobol_joe_kuo.npz` from SciPy's bundled Joe–Kuo table (run once, offline).

    python jaxmc/_data/make_sobol_data.py [MAX_DIM]

The file holds, for dimensions 1 .. MAX_DIM-1 (dimension 0 is van der Corput),
the primitive polynomials as first differences (`poly_diff`, uint16; `poly[0] = 1`)
and the initial direction numbers m_k (odd, < 2^k, k = 1 .. degree) bit-packed
as (m_k >> 1) in k-1 bits each, most significant bit first (`m_bits`). jaxmc
needs neither SciPy nor this script at run time.
"""

import os
import sys
from pathlib import Path

import numpy as np


def main(max_dim: int = 4096) -> None:
    import scipy.stats

    table = np.load(
        os.path.join(os.path.dirname(scipy.stats.__file__), "_sobol_direction_numbers.npz")
    )
    poly = table["poly"][:max_dim].astype(np.int64)
    vinit = table["vinit"][:max_dim].astype(np.int64)
    bits = []
    for i in range(1, max_dim):
        degree = int(poly[i]).bit_length() - 1
        for k in range(1, degree + 1):
            m = int(vinit[i, k - 1])
            assert m % 2 == 1 and m < 2**k
            bits += [((m >> 1) >> (k - 2 - t)) & 1 for t in range(k - 1)]
    out = Path(__file__).with_name("sobol_joe_kuo.npz")
    np.savez_compressed(
        out,
        poly_diff=np.diff(poly).astype(np.uint16),
        m_bits=np.packbits(np.array(bits, dtype=np.uint8)),
        max_dim=np.int64(max_dim),
    )
    print(f"wrote {out} ({out.stat().st_size} bytes, {max_dim} dimensions)")


if __name__ == "__main__":
    main(*(int(a) for a in sys.argv[1:]))
