"""``python -m tocabi_torchrl.export``: a checkpoint -> ONNX policy + JSON contract (+ TorchScript on request)."""

from __future__ import annotations

import argparse
import sys

from ..cli import RecipeParser


def build_parser() -> argparse.ArgumentParser:
    # Full option names only: an abbreviation such as --over would silently mean --overwrite.
    parser = RecipeParser(prog="python -m tocabi_torchrl.export", description=__doc__)
    parser.add_argument("--checkpoint", required=True, help="run folder or checkpoint .pt file")
    parser.add_argument("--out", required=True, help="ONNX file to write; the contract goes beside it as .json")
    parser.add_argument("--torchscript", action="store_true", help="also write a traced TorchScript module (.ts.pt)")
    parser.add_argument("--overwrite", action="store_true", help="replace existing output files")
    return parser


def main(argv: list[str] | None = None) -> None:
    args = build_parser().parse_args(argv)
    from .onnx_export import export_policy

    try:
        result = export_policy(args.checkpoint, args.out, torchscript=args.torchscript, overwrite=args.overwrite)
    except (OSError, ValueError, RuntimeError) as err:  # CheckpointError is a RuntimeError; OSError: --out unwritable
        sys.exit(f"error: {err}")
    except KeyboardInterrupt:  # every file is written atomically: nothing half-written is left
        print("stopped (Ctrl-C); no file is left half-written: run the export again (with --overwrite if it had "
              "written some of its files already)", file=sys.stderr)
        sys.exit(130)
    print(f"wrote {result.onnx} and {result.contract}" + (f" and {result.torchscript}" if result.torchscript else ""))
    if result.motion:
        print(f"copied the policy's reference motion to {result.motion} (it is none of the shipped motions; the "
              "runtime reads it beside the .onnx)")
    if result.removed_torchscript:
        print(f"removed {result.removed_torchscript}: a TorchScript module of the export this one replaced (pass "
              "--torchscript to write this policy's)")


if __name__ == "__main__":
    main(sys.argv[1:])
