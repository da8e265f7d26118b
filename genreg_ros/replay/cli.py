"""genreg-replay: replay bags of RGB-D clouds through register_node and score it against ground truth.

    genreg-replay --bag cache/bags/redkitchen_val --gap 1                 # starts register_node itself
    genreg-replay --bag b1 --bag b2 --gap 5 --lockstep --report cache/replay/x
    genreg-replay --bag b --connect --namespace /robot                    # a node that is already running

How pairs are relayed, stamped, timed and accounted for: `genreg_ros.replay.harness`; the figures:
`genreg_ros.replay.scoring`. A checkpoint that does not exist is a one-line error.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from genreg_core.checkpoint import resolve_checkpoint
from genreg_core.config import OBJECT_MODEL
from genreg_core.errors import GenRegError
from genreg_ros.replay import harness
from genreg_ros.replay.harness import DEFAULT_PARAMS, ReplayError, ReplayOptions, replay, yaml_param


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="genreg-replay", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog=__doc__ + "\n" + (harness.__doc__ or "").split("\n\n", 1)[1])
    p.add_argument("--bag", action="append", required=True, help="bag folder (repeat for several)")
    p.add_argument("--gap", type=int, default=1, help="target = frame i, source = frame i + gap (bag clouds)")
    p.add_argument("--rate", type=float, default=1.0, help="playback speed factor; 0: as fast as possible")
    p.add_argument("--lockstep", action="store_true", help="wait for each pair's result before the next")
    p.add_argument("--keep-stamps", action="store_true",
                   help="publish the bag's stamps (default: shift each bag to start now)")
    p.add_argument("--namespace", default="", help="the node's namespace")
    p.add_argument("--connect", action="store_true", help="use a running register_node, do not start one")
    p.add_argument("--params-file", type=Path, default=DEFAULT_PARAMS)
    p.add_argument("--checkpoint", help="model.checkpoint for the node (default: the params file's)")
    p.add_argument("-p", "--param", action="append", default=[], metavar="NAME:=VALUE",
                   help="extra node parameter override (repeatable)")
    p.add_argument("--no-icp", action="store_true", help="skip the Open3D ICP baseline")
    p.add_argument("--report", type=Path, help="report folder (report.md, errors.png, trajectory.png)")
    p.add_argument("--startup-timeout", type=float, default=90.0)
    p.add_argument("--quiet", action="store_true")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    bad = [kv for kv in args.param if ":=" not in kv]
    if bad:
        print(f"genreg-replay: error: -p takes NAME:=VALUE, got {bad[0]!r}", file=sys.stderr)
        return 2
    options = ReplayOptions(
        gap=args.gap, rate=args.rate, lockstep=args.lockstep, keep_stamps=args.keep_stamps, namespace=args.namespace, connect=args.connect,
        params_file=args.params_file, checkpoint=args.checkpoint,
        node_params=dict(kv.split(":=", 1) for kv in args.param), icp=not args.no_icp,
        report_dir=args.report, startup_timeout=args.startup_timeout, verbose=not args.quiet,
    )
    try:
        if not args.connect:  # a missing checkpoint fails here, not after the node's start-up
            resolve_checkpoint(options.checkpoint or yaml_param(options.params_file, "model.checkpoint", OBJECT_MODEL))
        result = replay(args.bag, options)
    except (GenRegError, ReplayError, OSError, ValueError) as exc:
        print(f"genreg-replay: error: {exc}", file=sys.stderr)
        return 1
    print(result.text)
    if result.report is not None:
        print(f"report             {result.report}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
