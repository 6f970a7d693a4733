"""Desert terrain (paper 001): ripple normal maps and their mip pyramid, the dune surface,
bump mapping of ripples onto dunes, sand-grain texture, culling and LOD per quad, texture-space
shading with dune and ripple shadows, ray casting to the screen, sand-dust billboards, and a window
of quads with its own micro relief (the footprints of Fig. 18)."""

from ._detail import DetailMaps as DetailMaps
from ._detail import build_detail_maps as build_detail_maps
from ._detail import window_ripples as window_ripples
from ._dune import close_periodic as close_periodic
from ._dune import ray_cast_coherent as ray_cast_coherent
from ._dune import ray_cast_heightfield as ray_cast_heightfield
from ._dune import vertex_normals as vertex_normals
from ._dust import DustParticles as DustParticles
from ._dust import billboard_alpha as billboard_alpha
from ._dust import composite_billboards as composite_billboards
from ._dust import dust_particles as dust_particles
from ._grain import sand_grain_texture as sand_grain_texture
from ._lod import quad_corners as quad_corners
from ._lod import quad_levels as quad_levels
from ._lod import quad_screen_area as quad_screen_area
from ._lod import quad_visibility as quad_visibility
from ._normals import normal_pyramid as normal_pyramid
from ._normals import ripple_normal_map as ripple_normal_map
from ._render import TerrainMaps as TerrainMaps
from ._render import build_terrain_maps as build_terrain_maps
from ._render import plan_quads as plan_quads
from ._render import quad_capacities as quad_capacities
from ._render import render_terrain as render_terrain
from ._render import shade_quads as shade_quads
from ._render import shadow_steps as shadow_steps
from ._render import with_detail as with_detail
