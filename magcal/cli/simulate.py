"""``magcal simulate``: write a simulated data file whose true errors are known.

Example::

    magcal simulate --preset chi2017 --seed 1 -o chi2017.csv
    magcal simulate --preset chi2017 --timeseries --n 3000 -o walk.csv
"""

from __future__ import annotations

import argparse

from magcal.cli.commands import HELP
from magcal.core.errors import MagcalError
from magcal.data import io
from magcal.data.simulation import PRESETS, simulate, simulate_timeseries
from magcal.model.perturbations import parse_hidden
from magcal.model.plugins import reserved_names
from magcal.model.terms import check_effect_names


def register(subparsers) -> argparse.ArgumentParser:
    """Add the ``simulate`` subcommand."""

    presets = "; ".join(f"{name}: {p.description}" for name, p in PRESETS.items())
    parser = subparsers.add_parser(
        "simulate",
        help=HELP["simulate"],
        description=f"Simulate magnetometer readings with known errors and write them as magcal CSV. Presets: "
        f"{presets}.",
    )
    add_arguments(parser)
    parser.set_defaults(func=run)
    return parser


def add_arguments(parser) -> None:
    """The options of ``magcal simulate`` (separate so other front ends can reuse them)."""
    parser.add_argument("--preset", default="chi2017", help="simulation preset (default chi2017)")
    parser.add_argument("--seed", type=int, default=0, help="random seed; the same seed gives the same file")
    parser.add_argument(
        "--n",
        type=int,
        default=None,
        metavar="N",
        help="number of samples (default: the preset's, 1500 with --timeseries)",
    )
    parser.add_argument(
        "--noise",
        type=float,
        default=None,
        metavar="NT",
        help="noise per axis in nT: Gaussian sigma, or full width for a uniform-noise preset (default: the preset's)",
    )
    parser.add_argument(
        "--timeseries",
        action="store_true",
        help="a smooth rotation trajectory with time and temperature columns instead of random attitudes",
    )
    parser.add_argument(
        "--hidden",
        action="append",
        default=None,
        metavar="EFFECT[:SENSOR][=MAGNITUDE]",
        help="hide an effect in the data (implies --timeseries; repeatable), e.g. temperature_bias:2=3 "
        "(3 nT/K in sensor 2); magnitude in the effect's unit (docs/effects.md), default a "
        "clearly visible one; periodic_interference hides an effect outside the catalogue",
    )
    parser.add_argument(
        "--no-reference", action="store_true", help="leave the reference field out of the file (it will then be fitted)"
    )
    parser.add_argument("-o", "--output", required=True, metavar="FILE.csv", help="file to write")


def run(args) -> int:

    if args.preset not in PRESETS:
        raise MagcalError(f"unknown preset {args.preset!r}; known presets: {', '.join(sorted(PRESETS))}")
    if args.n is not None and args.n < 1:
        raise MagcalError(f"--n must be a positive number of samples, got {args.n}")
    if args.noise is not None and args.noise < 0:
        raise MagcalError(f"--noise must be >= 0 nT, got {args.noise}")
    common = dict(noise_nT=args.noise, seed=args.seed, with_reference=not args.no_reference)
    hidden: list = []
    if getattr(args, "hidden", None):
        heads = [spec.partition("=")[0] for spec in args.hidden]
        check_effect_names([h for h in heads if h.partition(":")[0].strip() not in reserved_names()], "--hidden")
        n_sensors = PRESETS[args.preset].truth().n_sensors
        hidden = []
        for spec in args.hidden:
            try:
                hidden.append(parse_hidden(spec, n_sensors))
            except NotImplementedError:  # an effect (a user's) without a perturbation
                raise MagcalError(
                    f"--hidden {spec!r}: the effect has no perturbation(), so the simulator cannot "
                    "hide it; define perturbation(magnitude, sensor) in its class "
                    "(docs/user-effects.md)"
                ) from None
        args.timeseries = True
    if args.timeseries:
        ds = simulate_timeseries(args.preset, n_samples=args.n or 1500, perturbations=hidden, **common)
    else:
        ds = simulate(args.preset, n_samples=args.n, **common)
    meta = {"preset": args.preset, "seed": str(args.seed), "mode": "timeseries" if args.timeseries else "random"}
    io.write_csv(args.output, ds, metadata=meta)
    print(f"wrote {args.output}: {ds.describe()}")
    if hidden:  # not written into the file, so that it can be used as a blind exercise
        print("hidden: " + "; ".join(p.description for p in hidden))
    return 0
