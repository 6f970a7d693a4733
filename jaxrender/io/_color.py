"""Colour transfer functions and tone mapping; work on numpy and JAX arrays alike."""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float


def srgb_to_linear(x: ArrayLike) -> Float[Array, "..."]:
    """IEC 61966-2-1 decoding of values in [0, 1]."""
    x = jnp.asarray(x)
    return jnp.where(x <= 0.04045, x / 12.92, ((jnp.maximum(x, 0.04045) + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(x: ArrayLike) -> Float[Array, "..."]:
    """IEC 61966-2-1 encoding, clamped to [0, 1]."""
    x = jnp.clip(jnp.asarray(x), 0.0, 1.0)
    return jnp.where(x <= 0.0031308, 12.92 * x, 1.055 * jnp.maximum(x, 0.0031308) ** (1 / 2.4) - 0.055)


def luminance(rgb: Float[ArrayLike, "... 3"]) -> Float[Array, "..."]:
    """Rec. 709 / sRGB-primaries luminance."""
    rgb = jnp.asarray(rgb)
    return 0.2126 * rgb[..., 0] + 0.7152 * rgb[..., 1] + 0.0722 * rgb[..., 2]


def tonemap(image: Float[ArrayLike, "H W C"], *, exposure: float = 1.0, method: str = "aces") -> Float[Array, "H W C"]:
    """Linear HDR radiance -> display values in [0, 1], sRGB-encoded, for previews.

    `method`: "aces" (Narkowicz's fit of the ACES filmic curve), "reinhard" (x / (1 + x)),
    or "clip" (plain clamp: what the paper's 8-bit frame buffer shows).
    """
    # the curves saturate long before 1e4; clipping there keeps x * x finite for any finite radiance
    x = jnp.clip(jnp.asarray(image) * exposure, 0.0, 1e4)
    if method == "aces":
        x = (x * (2.51 * x + 0.03)) / (x * (2.43 * x + 0.59) + 0.14)
    elif method == "reinhard":
        x = x / (1.0 + x)
    elif method != "clip":
        raise ValueError(f"unknown tone mapping {method!r}: use aces, reinhard or clip")
    return linear_to_srgb(x)
