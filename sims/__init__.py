"""Simulations that feed the renderer: ripple and dune automata, sand dust, fire, cloth."""

from ._transport import creep as creep
from ._transport import deposit as deposit
from ._transport import saltate as saltate
from .dunes import DuneParams as DuneParams
from .dunes import dune_step as dune_step
from .dunes import dune_transport as dune_transport
from .dunes import init_dunes as init_dunes
from .dunes import simulate_dunes as simulate_dunes
from .ripples import RippleParams as RippleParams
from .ripples import dominant_wavelength as dominant_wavelength
from .ripples import init_ripples as init_ripples
from .ripples import power_spectrum_along as power_spectrum_along
from .ripples import ripple_step as ripple_step
from .ripples import simulate_ripples as simulate_ripples
from .ripples import spectral_centroid_wavelength as spectral_centroid_wavelength
from ._fields import load_field as load_field
from ._fields import preview_image as preview_image
from ._fields import save_field as save_field
from ._fields import simulate_in_chunks as simulate_in_chunks
from .dust import DustParams as DustParams
from .dust import advect_dust as advect_dust
from .dust import dust_sizes as dust_sizes
from .dust import init_dust as init_dust
from .dust import sample_periodic as sample_periodic
from .dust import simulate_dust as simulate_dust
