"""The `veinmosaic` command line: a thin shell over services/ (serving starts api/ and workers/ as processes)."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from cli import commands_offline, commands_service


class _Help(argparse.ArgumentDefaultsHelpFormatter):
    """Help that shows every option's default (and keeps the description's line breaks)."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = action.help or ""
        if action.default is None or action.default is argparse.SUPPRESS or action.default is False:
            return text
        if action.default in ([], "") or "(default" in text or not action.option_strings:
            return text
        return text + " (default: %(default)s)"


def build_parser() -> argparse.ArgumentParser:
    """Return the argument parser of the veinmosaic command."""
    parser = argparse.ArgumentParser(prog="veinmosaic", description=__doc__, formatter_class=_Help)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def command(name: str, help_text: str) -> argparse.ArgumentParser:
        return sub.add_parser(name, help=help_text, description=help_text, formatter_class=_Help)

    commands_offline.add_commands(command)
    commands_service.add_commands(command)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Return the exit code of running the veinmosaic command line."""
    from services.core.inputs.calibration import CalibrationError
    from services.store.scan_folder import ScanFormatError

    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args))
    except (ScanFormatError, CalibrationError, ValueError) as exc:
        print(f"veinmosaic: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
