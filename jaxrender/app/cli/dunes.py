"""`sims dunes --out FIELD.npy`: grow dunes (paper 001 eqs. 5-6).

A thin layer over `sims.init_dunes` and `sims.simulate_dunes`."""

from __future__ import annotations

import argparse

from sims import DuneParams, init_dunes, simulate_dunes

from .arguments import number
from .fields import add_common, execute


def configure(parser: argparse.ArgumentParser) -> None:
    add_common(parser, L0=7.0, b=2.0, D=0.8, size="64", steps=2000)
    parser.add_argument("--q0", type=number, default=1.5, help="sand moved on flat ground (default 1.5)")
    parser.add_argument("--b-prime", type=number, default=2.0, help="slope coefficient b' of the amount (default 2.0)")


def run(args: argparse.Namespace) -> int:
    params = DuneParams(L0=args.L0, q0=args.q0, b=args.b, b_prime=args.b_prime, D=args.D,
                        wind_deg=args.wind_deg, hop=args.hop)
    return execute(args, simulate=lambda h, steps: simulate_dunes(h, params, steps=steps),
                   init_random=lambda key, shape: init_dunes(key, shape), desc="dunes")
