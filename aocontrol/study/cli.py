"""Command line of aocontrol: science cases, simulations, comparisons, designs, sweeps.

Commands (``aocontrol COMMAND --help`` for each)::

    aocontrol cases                         the science cases and their parameters
    aocontrol run CASE --controller C --scheme S [--seconds S] [--seed N] [--out DIR]
    aocontrol compare CASE [--quick] [--out DIR]
    aocontrol design TELEMETRY [--loop NAME] [--fs F --latency L] [--controller datadriven]
                     [--order 5] [--out FILE.h5|.fits|.csv] [--export FILE.fits|.csv]
                     [--aot-out FILE] [--unit U] [--command-sign -1] [--override-metadata]
                     [--scheduler ADDRESS | --workers N]
    aocontrol sweep SPEC.toml [--scheduler ADDRESS] [--out DIR]
    aocontrol adapt CASE [--scenario S] [--period 2] [--window T] [--seconds 60] [--quick]
    aocontrol demo [--output DIR]

Exit status 0 on success, 2 for a user error (bad name, unreadable file: one line on stderr,
no traceback), 1 when a run fails (e.g. a diverging loop).

This module parses and dispatches; each command group's handlers live in a private module:
``_cli_simulate`` (cases, run, compare), ``_cli_design`` (design), ``_cli_studies`` (sweep,
demo, adapt), over the shared errors and tables of ``_cli_common``.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Callable

from aocontrol.study._cli_common import (  # noqa: F401 - UserError is part of this module's API
    RUN_SCHEMES,
    RunFailed,
    UserError,
    run_controller_names,
)
from aocontrol.study._cli_design import (  # noqa: F401 - read_telemetry is part of this API
    DESIGN_DESCRIPTION,
    _design,
    _design_report,
    design_arguments,
    read_telemetry,
)
from aocontrol.study._cli_simulate import _cases, _compare, _run, write_comparison
from aocontrol.study._cli_studies import (
    ADAPT_LATENCY,
    ADAPT_N_GRID,
    ADAPT_ORDER,
    ADAPT_PERIOD,
    ADAPT_WINDOW,
    _adapt,
    _demo,
    _sweep,
)

__all__ = ["main", "UserError", "read_telemetry", "write_comparison"]

logger = logging.getLogger(__name__)


# ----------------------------------------------------------------------------- parser
def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="aocontrol",
        description="Adaptive-optics control toolbox: design, analyse and score AO controllers.",
        epilog="Run 'aocontrol COMMAND --help' for the options of a command.",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log INFO messages")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def add(
        name: str, func: Callable, help_: str, description: str | None = None
    ) -> argparse.ArgumentParser:
        p = sub.add_parser(
            name,
            help=help_,
            description=description or help_,
            formatter_class=argparse.RawDescriptionHelpFormatter,
        )
        p.set_defaults(func=func)
        return p

    def no_progress(p: argparse.ArgumentParser) -> None:
        p.add_argument("--no-progress", action="store_true", help="hide progress bars")

    def case_settings(p: argparse.ArgumentParser) -> None:
        p.add_argument(
            "--set",
            action="append",
            default=[],
            metavar="KEY=VALUE",
            help="replace a case value for this run, e.g. --set seeing=0.6 or a model error "
            "--set stage2.latency_error=0.3 --set stage2.dm_time_constant='0.2 ms' "
            "(repeatable; keys of 'aocontrol cases', checked like a case file)",
        )

    def sensor_options(p: argparse.ArgumentParser) -> None:
        from aocontrol.study.cases import OPTICAL_GAIN_SETTINGS, SENSORS

        p.add_argument(
            "--sensor",
            choices=SENSORS,
            default=None,
            help="stage-2 sensor in the loop (default: the case's, linear)",
        )
        p.add_argument(
            "--optical-gain",
            choices=OPTICAL_GAIN_SETTINGS,
            default=None,
            help="stage-2 optical-gain handling (default: the case's, calibrated)",
        )

    add("cases", _cases, "list the science cases and their parameters")

    p = add("run", _run, "simulate one case with one controller; write a results file")
    p.add_argument("case", help="science case name (see 'aocontrol cases') or a case .toml")
    p.add_argument(
        "--controller",
        required=True,
        metavar="{" + ",".join(run_controller_names()) + "}",
        help="controller of the (fast) stage (aocontrol.synthesis.CONTROLLERS; integrator is "
        "an alias of reference)",
    )
    p.add_argument(
        "--scheme",
        required=True,
        metavar="{" + ",".join(RUN_SCHEMES) + "}",
        help="single stage, standalone cascade or dCAO cascade",
    )
    p.add_argument(
        "--seconds",
        type=float,
        default=None,
        help="simulated time [s] (default: the comparison protocol's)",
    )
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--out", default="results", help="folder of the results file and plots")
    p.add_argument("--quick", action="store_true", help="reduced modes and pupil (smoke runs)")
    p.add_argument("--telemetry", action="store_true", help="also store the telemetry")
    sensor_options(p)
    case_settings(p)
    no_progress(p)

    p = add("compare", _compare, "the paper's comparison of one case: table, plots, HTML report")
    p.add_argument("case", help="science case name (see 'aocontrol cases')")
    p.add_argument("--quick", action="store_true", help="short, reduced runs")
    p.add_argument("--out", default="compare-output", help="folder of the table and plots")
    sensor_options(p)
    case_settings(p)
    no_progress(p)

    p = add(
        "design",
        _design,
        "design a controller bank from closed-loop telemetry",
        description=DESIGN_DESCRIPTION,
    )
    design_arguments(p)
    no_progress(p)

    p = add("sweep", _sweep, "run a sweep spec (cases x controllers x schemes x seeds) on Dask")
    p.add_argument("spec", help="sweep spec (TOML)")
    p.add_argument(
        "--scheduler", default=None, help="Dask scheduler address (default: a local cluster)"
    )
    p.add_argument("--out", default="sweep-output", help="results folder")
    no_progress(p)

    p = add(
        "adapt",
        _adapt,
        "adaptive control under drifting turbulence: residual against update period and window",
    )
    p.epilog = (
        "Defaults are the study's recommended configuration (docs/adaptive.md): T = 2 s, "
        "W = T, design latency 0.5 s, order 2 and a 24-point design grid with --quick (order 5 "
        "and the synthesis' grid otherwise). A multi-knot drift: a case file's "
        '[atmosphere.drift] kind = "knots" with --scenario case. Cost: a 60-s quick run '
        "(24 modes, five strategies) takes a few CPU minutes per scenario."
    )
    p.add_argument("case", help="science case name (see 'aocontrol cases') or a case .toml")
    p.add_argument(
        "--scenario",
        default="wind-doubles",
        help="wind-doubles, seeing-worsens, stochastic, or case (the case file's "
        "[atmosphere.drift], any number of knots); comma-separated for several "
        "(default wind-doubles)",
    )
    p.add_argument(
        "--period",
        default=ADAPT_PERIOD,
        help=f"update periods T [s], comma-separated (default {ADAPT_PERIOD})",
    )
    p.add_argument(
        "--window",
        default=ADAPT_WINDOW,
        help="telemetry windows W: seconds, 'T' (the period) or 'max(T, x)', comma-separated "
        f"(default {ADAPT_WINDOW}: each redesign from all the telemetry since the last)",
    )
    p.add_argument("--seconds", type=float, default=60.0, help="simulated time [s] (default 60)")
    p.add_argument(
        "--strategies",
        default=None,
        help="comma-separated among fixed, adaptive, oracle, modal-gain, lqg (default all "
        "five), the multi-mode predictor trained once or retrained, eof-fixed and eof, and "
        "the diagnostics adaptive-nolatency, adaptive-truth, oracle-prophet",
    )
    p.add_argument(
        "--latency",
        type=float,
        default=ADAPT_LATENCY,
        help=f"design latency [s] (default {ADAPT_LATENCY:g}; negative: the measured compute time)",
    )
    p.add_argument(
        "--order",
        type=int,
        default=None,
        help=f"data-driven controller order (default {ADAPT_ORDER[True]} with --quick, "
        f"{ADAPT_ORDER[False]} otherwise)",
    )
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument(
        "--jobs", type=int, default=1, help="worker processes of each design (default 1)"
    )
    p.add_argument(
        "--quick", action="store_true", help="reduced modes and pupil (24 stage-2 modes)"
    )
    p.add_argument(
        "--select",
        type=float,
        default=None,
        help="redesign only the modes covering this share of the residual shift, e.g. 0.9 "
        "(default: every mode)",
    )
    p.add_argument(
        "--n-grid",
        type=int,
        default=None,
        help=f"data-driven design grid size (default {ADAPT_N_GRID[True]} with --quick, the "
        "synthesis' own otherwise)",
    )
    p.add_argument(
        "--max-iter",
        type=int,
        default=None,
        help="data-driven iterations of a cold design (default: the synthesis' own)",
    )
    p.add_argument(
        "--measure-from",
        type=float,
        default=None,
        help="time [s] from which every row's residual is averaged (default: each row's own "
        "window; the study's tables use 6 s of 60)",
    )
    p.add_argument(
        "--out",
        default="adapt-output",
        help="folder of the table, HDF5 and plot (default adapt-output)",
    )

    p = add(
        "demo",
        _demo,
        "design controllers for one mode and plot the rejection, then a short comparison "
        "on a science case (table and contrast plot)",
    )
    p.add_argument("--output", default="demo-output", help="folder for the plots and tables")
    p.add_argument("--case", default="red1-fast", help="science case of the comparison")
    p.add_argument(
        "--no-comparison", action="store_true", help="only the one-mode design (seconds)"
    )
    p.add_argument("--fs", type=float, default=3000.0, help="loop rate [Hz]")
    p.add_argument(
        "--latency", type=float, default=0.83, help="RTC latency beyond WFS integration [frames]"
    )
    p.add_argument(
        "--noise-rms", type=float, default=2.0, help="modal measurement noise [nm RMS per frame]"
    )
    no_progress(p)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``aocontrol`` command (console script and ``python -m aocontrol``).

    Parameters
    ----------
    argv : list of str, optional
        Arguments without the program name (default ``sys.argv[1:]``).

    Returns
    -------
    int
        Exit status: 0 success, 1 failed run, 2 user error (argparse also exits with 2).
    """
    args = _parser().parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
    )
    try:
        return args.func(args)
    except (UserError, ValueError, TypeError, OSError) as exc:
        print(f"aocontrol {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except RunFailed as exc:
        print(f"aocontrol {args.command}: failed: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"aocontrol {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
