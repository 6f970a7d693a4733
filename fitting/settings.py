"""The settings of a fit: one frozen value, checked once where a user's arguments enter (the
`fitting fit` command line or a `fitting.fit_*` call), then passed whole through the engine.

    FitSettings()                                   # robust method, optimistix, chunks of 4096 texels
    FitSettings(method="plain", solver="native")    # ValueError for a value that is not allowed
"""

from __future__ import annotations

import dataclasses

from jaxrender.brdf import MODELS

__all__ = ["FitSettings", "METHODS", "SOLVERS", "DEFAULT_METHOD", "DEFAULT_SOLVER", "DEFAULT_CHUNK",
           "DEFAULT_MAX_STEPS", "DEFAULT_MODEL"]

# "robust" (default, every capture): materials shared by the texels give each texel's lobe a prior,
# shadows and highlights are outliers (docs/fitting.md, "Real captures: the robust method");
# "plain": per-texel least squares (paper 004).
METHODS = ("robust", "plain")
SOLVERS = ("optimistix", "native", "jaxopt")   # fitting.lm_optimistix, lm_native, lm_jaxopt
DEFAULT_METHOD = "robust"
DEFAULT_SOLVER = "optimistix"
DEFAULT_CHUNK = 4096      # texels per chunk: one checkpoint file, one Dask task
DEFAULT_MAX_STEPS = 40    # Levenberg-Marquardt steps per solve
DEFAULT_MODEL = "reciprocal"
_METHOD_TEXT = {"robust": "levenberg-marquardt, variable projection of rho_d, rho_s; material priors, "
                          "robust geometry rounds with an ambient term, appearance round",
                "plain": "levenberg-marquardt, variable projection of rho_d, rho_s"}


@dataclasses.dataclass(frozen=True)
class FitSettings:
    """How every texel is fitted. Hashable: it keys the compiled programs and the checkpoints.

    `method`: "robust" or "plain" (`METHODS`); `solver`: the Levenberg-Marquardt backend
    (`SOLVERS`); `chunk`: texels per chunk (bounds memory; one checkpoint file and one Dask task
    each); `max_steps`: solver steps per solve; `model`: the BRDF's form (`jaxrender.brdf.MODELS`).
    """

    method: str = DEFAULT_METHOD
    solver: str = DEFAULT_SOLVER
    chunk: int = DEFAULT_CHUNK
    max_steps: int = DEFAULT_MAX_STEPS
    model: str = DEFAULT_MODEL

    def __post_init__(self):
        if self.method not in METHODS:
            raise ValueError(f"unknown method {self.method!r}: use one of {METHODS}")
        if self.solver not in SOLVERS:
            raise ValueError(f"unknown solver {self.solver!r}: use one of {SOLVERS}")
        if self.model not in MODELS:
            raise ValueError(f"unknown model {self.model!r}: use one of {MODELS}")
        for name in ("chunk", "max_steps"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")

    @property
    def robust(self) -> bool:
        return self.method == "robust"

    def program(self) -> "FitSettings":
        """The settings that shape the compiled per-texel program: all but the chunk (one program
        for every chunk size)."""
        return dataclasses.replace(self, chunk=DEFAULT_CHUNK)

    def key(self) -> dict:
        """Every field, for a checkpoint's fingerprint (another value: another fit)."""
        return dataclasses.asdict(self)

    def describe(self) -> dict:
        """The fit's entry in `btf.json` (`fit`: solver, method, chunk, max_steps)."""
        return {"solver": self.solver, "method": _METHOD_TEXT[self.method], "chunk": self.chunk,
                "max_steps": self.max_steps}
