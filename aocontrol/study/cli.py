"""Command line: ``aocontrol demo`` (more jobs come with the study layer)."""

from __future__ import annotations

import argparse
import logging
import sys

__all__ = ["main"]


def _demo(args: argparse.Namespace) -> int:
    from aocontrol.study.demo import run_demo

    res = run_demo(args.output, fs=args.fs, latency_frames=args.latency, noise_rms=args.noise_rms)
    print(
        f"Loop: fs = {res.fs:g} Hz, latency = {res.latency_frames} frame (+1 frame WFS integration)"
    )
    header = (
        f"{'controller':34s} {'stable':>6s} {'GM':>7s} {'PM[deg]':>8s} "
        f"{'MM':>6s} {'DM[fr]':>7s} {'resid[nm]':>9s}"
    )
    print(header)
    print("-" * len(header))
    for name, m in res.margins.items():
        print(
            f"{name:34s} {str(m.stable):>6s} {m.gain_margin:7.2f} {m.phase_margin:8.1f} "
            f"{m.modulus_margin:6.3f} {m.delay_margin:7.2f} {res.residual_rms[name]:9.2f}"
        )
    print(
        f"{'physical limit (Wiener bound)':34s} {'':>6s} {'':>7s} {'':>8s} {'':>6s} {'':>7s} "
        f"{res.wiener_rms:9.2f}"
    )
    print(f"Rejection plot written to {res.plot_path}")
    return 0


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``aocontrol`` command."""
    parser = argparse.ArgumentParser(prog="aocontrol", description=__doc__)
    parser.add_argument("-v", "--verbose", action="store_true", help="log INFO messages")
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("demo", help="design controllers for one mode and plot the rejection")
    p.add_argument("--output", default="demo-output", help="folder for the plot")
    p.add_argument("--fs", type=float, default=3000.0, help="loop rate [Hz]")
    p.add_argument(
        "--latency", type=float, default=0.83, help="RTC latency beyond WFS integration [frames]"
    )
    p.add_argument(
        "--noise-rms", type=float, default=2.0, help="modal measurement noise [nm RMS per frame]"
    )
    p.set_defaults(func=_demo)
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
    )
    try:
        return args.func(args)
    except (ValueError, TypeError) as exc:
        print(f"aocontrol {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
