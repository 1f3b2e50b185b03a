"""``amuled study build|serve|analyze|export|fit-weights``: people judge the trained agents."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from amuled_ma.commands import _experiment as common


def _warn(line: str) -> None:
    """One ``amuled: warning: ...`` line on stderr."""
    print(f"amuled: warning: {line}", file=sys.stderr, flush=True)


def _variants(text: str) -> list[str]:
    return [v.strip() for v in text.split(",") if v.strip()]


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``amuled study`` and its sub-commands."""
    parser = subparsers.add_parser(
        "study",
        help="build, serve and analyse a study where people judge the agents' decisions",
        description=(
            "A study shows people states the trained policies met, with two variants' "
            "decisions side by side (blinded, in random order), and stores their choices."
        ),
    )
    parser.set_defaults(handler=lambda args: parser.print_help() or 2)
    sub = parser.add_subparsers(dest="study_command", metavar="COMMAND")

    build = sub.add_parser("build", help="write a study folder from runs")
    build.add_argument("runs", metavar="RUN", nargs="+", type=Path, help="run folders")
    build.add_argument(
        "--variants",
        type=_variants,
        default=["amuled", "base"],
        help="comma-separated variants to compare (default amuled,base)",
    )
    build.add_argument("--items", type=common.bounded_int(1), default=40, help="pairs to ask")
    build.add_argument("--seed", type=common.bounded_int(0), default=0, help="the draw's seed")
    build.add_argument(
        "--attention",
        type=common.bounded_int(0),
        default=None,
        help="attention checks (default: one per ten pairs, at least one)",
    )
    build.add_argument(
        "--episodes",
        type=common.bounded_int(1),
        default=3,
        help="evaluation episodes replayed per variant to find states (default 3)",
    )
    build.add_argument("--out", type=Path, required=True, help="the study folder to write")
    build.add_argument("--force", action="store_true", help="rebuild an existing study")
    build.add_argument(
        "--mode",
        choices=("pairs", "expert"),
        default="pairs",
        help="pairs: people choose between two variants' decisions and rate each one's "
        "acceptability; expert: experts judge every action of a state with the panel's "
        "reasons (default pairs)",
    )
    build.set_defaults(handler=_build)

    serve = sub.add_parser("serve", help="serve a study to participants")
    serve.add_argument("study", metavar="STUDY", type=Path, help="a study folder")
    serve.add_argument(
        "--host",
        default="127.0.0.1",
        help="address to listen on (default 127.0.0.1, this machine only; any other "
        "address needs --public)",
    )
    serve.add_argument(
        "--public",
        action="store_true",
        help="allow a --host other machines can reach (0.0.0.0: every interface); a "
        "warning line says so",
    )
    serve.add_argument("--port", type=common.bounded_int(1, 65535), default=8765)
    serve.add_argument(
        "--allow-placeholder-consent",
        action="store_true",
        help="serve a consent.html that still holds the template's [placeholders] (a trial run)",
    )
    serve.set_defaults(handler=_serve)

    analyze = sub.add_parser("analyze", help="write the study's report")
    analyze.add_argument("study", metavar="STUDY", type=Path, help="a study folder")
    analyze.add_argument(
        "--keep-inattentive",
        action="store_true",
        help="keep the answers of participants who failed an attention check",
    )
    analyze.set_defaults(handler=_analyze)

    export = sub.add_parser("export", help="the answers as CSV")
    export.add_argument("study", metavar="STUDY", type=Path, help="a study folder")
    export.add_argument(
        "-o", "--output", type=Path, default=None, help="CSV file (default: stdout)"
    )
    export.set_defaults(handler=_export)

    fit = sub.add_parser(
        "fit-weights",
        help="learn a weight per panel member from the answers ([feedback].weights)",
        description=(
            "Fit a prior weight per panel member so that the bjs-dst fused belief best "
            "predicts the participants' choices (maximum likelihood, 95% bootstrap "
            "intervals over participants, held-out log-likelihood against the paper's "
            "fixed weights) and write it for [feedback].weights (docs/study.md)."
        ),
    )
    fit.add_argument("study", metavar="STUDY", type=Path, help="a study folder")
    fit.add_argument(
        "--bootstrap",
        type=common.bounded_int(1, 100_000),
        default=200,
        help="resamples of the participants for the intervals (default 200)",
    )
    fit.add_argument(
        "--folds",
        type=common.bounded_int(2, 1000),
        default=5,
        help="folds of participants for the held-out log-likelihood (default 5)",
    )
    fit.add_argument(
        "--seed", type=common.bounded_int(0, 2**63 - 1), default=0, help="seed (default 0)"
    )
    fit.add_argument(
        "-o",
        "--output",
        type=Path,
        default=None,
        help="the weights file (default STUDY/analysis/weights.json)",
    )
    fit.add_argument(
        "--temperature",
        type=common.positive_float,
        default=None,
        metavar="T",
        help="fix the choice model's temperature (1: Luce's rule on the fused belief); "
        "default: fitted with the weights",
    )
    fit.add_argument(
        "--keep-inattentive",
        action="store_true",
        help="keep the answers of participants who failed an attention check",
    )
    fit.add_argument("--no-progress", action="store_true", help="no progress bar")
    fit.set_defaults(handler=_fit_weights)


def _build(args: argparse.Namespace) -> int:
    from amuled_ma.study.model import check_run_folders

    check_run_folders(args.runs)  # before the heavy imports of the build (torch)
    from amuled_ma.study.build import build_study

    study = build_study(
        args.runs,
        args.variants,
        args.out,
        items=args.items,
        seed=args.seed,
        attention=args.attention,
        episodes=args.episodes,
        force=args.force,
        mode=args.mode,
    )
    pairs = sum(1 for i in study.items if i.kind == "pair")
    what = (
        f"{len(study.items)} states of {study.candidates} met, for experts"
        if study.mode == "expert"
        else f"{pairs} pairs of {study.candidates} candidates and "
        f"{len(study.items) - pairs} attention checks"
    )
    common.say(
        f"study {args.out}: {what}; edit {args.out / 'consent.html'}, "
        f"then 'amuled study serve {args.out}'"
    )
    return 0


def _serve(args: argparse.Namespace) -> int:
    from amuled_ma.study.server import serve

    serve(
        args.study,
        host=args.host,
        port=args.port,
        public=args.public,
        allow_placeholder_consent=args.allow_placeholder_consent,
        say=common.say,
    )
    return 0


def _analyze(args: argparse.Namespace) -> int:
    from amuled_ma.study.report import write_analysis

    path = write_analysis(args.study, keep_inattentive=args.keep_inattentive, warn=_warn)
    common.say(f"study {args.study}: report {path}")
    return 0


def _export(args: argparse.Namespace) -> int:
    from amuled_ma.files.safe import check_write_target, write_text_atomic
    from amuled_ma.study.analysis import answers_csv

    if args.output is not None:
        check_write_target(args.output)  # before the answers are read
    text = answers_csv(args.study)
    if args.output is None:
        sys.stdout.write(text)
    else:
        write_text_atomic(args.output, text)
        common.say(f"study {args.study}: answers written to {args.output}")
    return 0


def _fit_weights(args: argparse.Namespace) -> int:
    from amuled_ma.study.weights import fit_weights, summary_lines

    weights, path = fit_weights(
        args.study,
        bootstrap=args.bootstrap,
        folds=args.folds,
        seed=args.seed,
        keep_inattentive=args.keep_inattentive,
        temperature=args.temperature,
        out=args.output,
        progress=not args.no_progress,
    )
    for line in summary_lines(weights):
        common.say(line)
    common.say(f"study {args.study}: weights {path} (name it in a scenario: [feedback] weights)")
    return 0
