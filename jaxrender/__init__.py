"""jaxrender: differentiable rendering kernels and scenes in pure JAX.

Light shafts in fog (paper 000), desert dunes with wind ripples (paper 001) and woven fabric
under environment light and firelight (paper 004). Kernel submodules: `io`, `textures`, `camera`,
`brdf`, `geometry`, `lights`, `shadows`, `shafts`, `fabric`, `terrain`, `sky`, `maths`, `fusion`;
the showcase scenes, gallery and command lines are the orchestration layer `jaxrender.app`
(`jaxrender.app.scenes.load_shafts_scene`, ...), which `import jaxrender` does not load.
"""

__version__ = "0.2.0"
