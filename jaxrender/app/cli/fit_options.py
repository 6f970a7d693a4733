"""The options of a fit's settings, shared by `fitting fit` and `fitting evaluate`: added to a
parser by `add_fit_settings`, turned into the one `fitting.FitSettings` value by `fit_settings`."""

from __future__ import annotations

from fitting import FitSettings
from fitting.settings import (
    DEFAULT_CHUNK,
    DEFAULT_MAX_STEPS,
    DEFAULT_METHOD,
    DEFAULT_MODEL,
    DEFAULT_SOLVER,
    METHODS,
    SOLVERS,
)
from jaxrender.brdf import MODELS

from .arguments import positive_int


def add_fit_settings(parser) -> None:
    parser.add_argument("--method", choices=METHODS, default=DEFAULT_METHOD,
                        help=f"default {DEFAULT_METHOD}: materials shared by the texels, shadows and highlights as "
                             "outliers (measured captures); plain: per-texel least squares (paper 004)")
    parser.add_argument("--solver", choices=SOLVERS, default=DEFAULT_SOLVER,
                        help=f"Levenberg-Marquardt backend (default {DEFAULT_SOLVER}; native = fitting.lm_native's "
                             "own loop)")
    parser.add_argument("--chunk", type=positive_int, default=DEFAULT_CHUNK,
                        help=f"texels per chunk: bounds memory, one checkpoint each (default {DEFAULT_CHUNK})")
    parser.add_argument("--max-steps", type=positive_int, default=DEFAULT_MAX_STEPS,
                        help=f"Levenberg-Marquardt steps per solve (default {DEFAULT_MAX_STEPS})")
    parser.add_argument("--model", choices=MODELS, default=DEFAULT_MODEL,
                        help=f"model form (default {DEFAULT_MODEL}; paper = eq. 1 as printed)")


def fit_settings(args) -> FitSettings:
    return FitSettings(method=args.method, solver=args.solver, chunk=args.chunk, max_steps=args.max_steps,
                       model=args.model)
