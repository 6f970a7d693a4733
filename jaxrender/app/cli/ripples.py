"""`sims ripples --out FIELD.npy`: grow wind ripples (paper 001 eqs. 1-4).

A thin layer over `sims.init_ripples` and `sims.simulate_ripples`."""

from __future__ import annotations

import argparse

from sims import RippleParams, init_ripples, simulate_ripples

from .arguments import number
from .fields import add_common, execute


def configure(parser: argparse.ArgumentParser) -> None:
    add_common(parser, L0=7.3, b=2.0, D=0.8, size="128", steps=3000)
    parser.add_argument("--q", type=number, default=0.6, help="sand moved by one hop (default 0.6)")


def run(args: argparse.Namespace) -> int:
    params = RippleParams(L0=args.L0, q=args.q, b=args.b, D=args.D, wind_deg=args.wind_deg, hop=args.hop)
    return execute(args, simulate=lambda h, steps: simulate_ripples(h, params, steps=steps),
                   init_random=lambda key, shape: init_ripples(key, shape), desc="ripples")
