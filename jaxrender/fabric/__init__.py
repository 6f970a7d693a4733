"""Woven fabric rendering (paper 004): a rasterized garment G-buffer, BTF pyramids of 1 or 2 lobes
per texel with per-pixel mip selection, shading under environment and firelight samples, and the
glossy planar reflection of a polished floor."""

from ._raster import GBuffer as GBuffer
from ._raster import Pinhole as Pinhole
from ._raster import camera_pinhole as camera_pinhole
from ._raster import depth_map as depth_map
from ._raster import raster_window as raster_window
from ._raster import rasterize as rasterize
from ._raster import spot_pinhole as spot_pinhole
from ._reflection import fresnel_schlick as fresnel_schlick
from ._reflection import glossy_blur_pixels as glossy_blur_pixels
from ._reflection import glossy_reflection as glossy_reflection
from ._reflection import mirror_mesh as mirror_mesh
from ._reflection import reflect_directions as reflect_directions
from ._reflection import reflect_points as reflect_points
from ._shading import MaterialSet as MaterialSet
from ._shading import lookup_texels as lookup_texels
from ._shading import mip_level as mip_level
from ._shading import shade_fabric as shade_fabric
from ._shading import shade_samples as shade_samples
from ._shading import shade_single_lobe as shade_single_lobe
from ._shading import stack_materials as stack_materials
from ._shading import tangent_frames as tangent_frames
