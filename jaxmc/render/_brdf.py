r"""A diffuse base plus a Beckmann microfacet lobe: evaluation, sampling and pdf.

$$ f(\omega_o, \omega_i) = \frac{k_d}{\pi}
   + k_s \frac{D(h)\, G_1(\omega_i) G_1(\omega_o)}{4\cos\theta_i\cos\theta_o},
\qquad D(h) = \frac{e^{-\tan^2\theta_h/\alpha^2}}{\pi\alpha^2\cos^4\theta_h}, $$

with $h$ the half vector, Smith's shadowing for Beckmann (Walter et al. 2007,
rational approximation) and no Fresnel term (a conductor of unit
reflectance, as in Veach's scene). Sampling picks the glossy lobe with
probability $k_s / (k_s + \bar k_d)$ and then draws $h$ with density
$D(h)\cos\theta_h$ (so $\omega_i$ has density $D\cos\theta_h / 4|\omega_o\cdot h|$),
otherwise a cosine-weighted direction; the pdf is the mixture of the two.

Everything is written for one shading point and is smooth in $\alpha$, $k_d$
and $k_s$ (with the directions held fixed), so light-sampled images
differentiate cleanly with respect to the material.
"""

from __future__ import annotations

import jax.numpy as jnp

from .. import warps
from ._math import dot, normalize, reflect, safe_div, safe_sqrt, to_world


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


def pdf(diffuse, specular, alpha, n, wo, wi):
    """Solid-angle density of `sample` producing `wi`."""
    ci = dot(n, wi)
    p_spec = specular_probability(diffuse, specular)
    h = normalize(wi + wo)
    p_glossy = safe_div(beckmann_d(h, n, alpha) * dot(h, n), 4.0 * jnp.abs(dot(wo, h)))
    p = p_spec * p_glossy + (1.0 - p_spec) * ci / jnp.pi
    return jnp.where((ci > 0) & (dot(n, wo) > 0), p, 0.0)


def sample(diffuse, specular, alpha, n, wo, u):
    """Draw `wi` from `u ∈ [0,1)^2`; the first coordinate is re-used to pick the lobe."""
    p_spec = specular_probability(diffuse, specular)
    glossy = u[0] < p_spec
    u0 = jnp.where(glossy, safe_div(u[0], p_spec), safe_div(u[0] - p_spec, 1.0 - p_spec))
    u0 = jnp.clip(u0, 0.0, 1.0 - 1e-7)
    # Beckmann half vector: tan^2 theta_h = -alpha^2 log(1 - u0)
    tan_t = alpha * safe_sqrt(-jnp.log1p(-u0))
    cos_t = 1.0 / jnp.sqrt(1.0 + tan_t * tan_t)
    sin_t = tan_t * cos_t
    phi = 2.0 * jnp.pi * u[1]
    h = to_world(jnp.stack([sin_t * jnp.cos(phi), sin_t * jnp.sin(phi), cos_t]), n)
    wi_glossy = reflect(wo, h)
    wi_diffuse = to_world(warps.hemisphere_cosine(jnp.stack([u0, u[1]])), n)
    return jnp.where(glossy, wi_glossy, wi_diffuse)
