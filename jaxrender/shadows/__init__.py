"""Shadows: shadow maps rendered from lights, PCF/PCSS soft shadows, heightfield ray marching,
horizon maps. One private module per technique; public names re-exported here."""

from ._heightfield import heightfield_light as heightfield_light
from ._heightfield import heightfield_shadow as heightfield_shadow
from ._heightfield import triangle_height as triangle_height
from ._horizon import horizon_band as horizon_band
from ._horizon import horizon_directions as horizon_directions
from ._horizon import horizon_light as horizon_light
from ._horizon import horizon_map as horizon_map
from ._horizon import horizon_shadow as horizon_shadow
from ._pcss import pcf as pcf
from ._pcss import pcss as pcss
from ._shadow_map import ShadowMap as ShadowMap
from ._shadow_map import render_shadow_map as render_shadow_map
from ._shadow_map import shadow_test as shadow_test
from ._shadow_map import shadow_uv_distance as shadow_uv_distance
from ._shadow_map import texel_directions as texel_directions
