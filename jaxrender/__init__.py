"""jaxrender: differentiable rendering kernels and scenes in pure JAX.

Light shafts in fog (paper 000), desert dunes with wind ripples (paper 001) and woven fabric
under environment light and firelight (paper 004). Submodules: `io`, `textures`, `camera`,
`brdf`, `geometry`, `lights`, `shadows`, `shafts`, `terrain`, `sky`, `scenes`.
"""

__version__ = "0.1.0"
