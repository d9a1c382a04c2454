"""``groom batch INPUTS... --head MESH -o OUTDIR``: invert many grooms on Dask (docs/batch.md).

Wiring (cli/main.py): ``batch_cmd.add_parser(sub, inv)`` after the invert parser ``inv`` is built (the
batch takes every invert option from it, so both stay in step) and the ``COMMANDS`` entry "batch".
"""

from __future__ import annotations

import argparse
import sys

from .options import UserError, cli_message, invert_params

EPILOG = """examples:
  groom batch styles/*.data --head head_model.obj --contacts all -o out          # LocalCluster, 2 workers
  groom batch styles/*.data --head head_model.obj -o out --workers 8 --memory-limit 4GiB
  groom batch styles/*.data --head head_model.obj -o out --scheduler tcp://sched:8786   # a running cluster

outputs: OUTDIR/<input stem>/ (rest.npz, rest_shape.obj, fitted.obj, report.json, as groom invert),
         OUTDIR/batch_summary.csv and OUTDIR/batch_summary.json (one row per input)
resume:  a groom whose OUTDIR/<stem>/report.json exists is skipped (--no-resume recomputes it)
exit codes: 0 every groom inverted (or skipped), 1 an input error (or a crash / a worker lost too
            often) for at least one groom, 2 otherwise: some contact solve did not converge
"""

# invert options the batch does not take over: its own input, output and quiet
_NOT_SHARED = {"help", "input", "output", "quiet"}


def add_parser(sub, invert_parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    p = sub.add_parser("batch", help="invert many grooms on Dask (a local cluster or a scheduler), with resume "
                                     "and a summary table",
                       epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("inputs", nargs="+", metavar="INPUT", help="groom files (any format groom invert reads)")
    p.add_argument("-o", "--output", default="groom_batch",
                   help="output directory: one OUTDIR/<input stem>/ per groom (default ./groom_batch)")
    p.add_argument("--workers", type=int, default=2, metavar="N",
                   help="worker processes of the local cluster, one thread each (default 2; ignored with --scheduler)")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="a running Dask scheduler (tcp://host:8786) instead of a local cluster")
    p.add_argument("--memory-limit", default="auto", metavar="BYTES",
                   help="per local worker, e.g. 4GiB ('auto': the machine's memory shared out; 0: none); a worker "
                        "over it is restarted and its groom retried")
    p.add_argument("--retries", type=int, default=3, metavar="N",
                   help="reruns of a groom whose worker died (killed, out of memory) before it is reported "
                        "(local cluster; a scheduler's own distributed.scheduler.allowed-failures otherwise; default 3)")
    p.add_argument("--no-resume", dest="resume", action="store_false",
                   help="recompute grooms whose output set is already complete (default: skip them)")
    # every option of groom invert (same defaults and help), taken from its parser
    for action in invert_parser._actions:
        if action.dest not in _NOT_SHARED:
            p._add_action(action)
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar and no summary")
    return p


def cmd_batch(args) -> int:
    from ..batch import print_summary, run_batch
    from ..groom import UNIT_SCALE

    if args.workers < 1:
        raise UserError(f"--workers must be at least 1, got {args.workers}")
    if args.retries < 0:
        raise UserError(f"--retries must be 0 or more, got {args.retries}")
    if args.contacts == "head" and args.head is None:
        raise UserError("--contacts head needs --head MESH")
    try:
        params = invert_params(args, UNIT_SCALE[args.units])
    except ValueError as exc:
        raise UserError(str(exc)) from exc
    memory_limit = args.memory_limit
    if memory_limit != "auto":
        from dask.utils import parse_bytes

        try:
            memory_limit = parse_bytes(memory_limit)
        except ValueError as exc:
            raise UserError(f"--memory-limit {args.memory_limit!r}: not a size like 4GiB, 'auto' or 0") from exc
    formats = tuple(args.format) if args.format else ("npz", "obj", "json")
    summary = run_batch(args.inputs, args.output, head=args.head, params=params, units=args.units,
                        scale=getattr(args, "scale", 1.0), up=args.up,
                        repair=args.repair, strand_length=args.strand_length, formats=formats,
                        workers=args.workers, scheduler=args.scheduler, memory_limit=memory_limit,
                        retries=args.retries, resume=args.resume, quiet=args.quiet)
    if not args.quiet:
        print_summary(summary)
    for r in summary.failed():  # library advice -> the CLI's flags
        print(f"groom batch: {r['name']}: {r['status']}: {cli_message(r['error'] or '')}", file=sys.stderr)
    return summary.exit_code
