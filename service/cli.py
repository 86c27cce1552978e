"""``shadowcorr serve``: argparse front end of :func:`service.serve`.

The integrator wires it into the main CLI with::

    from shadowcorr_service.cli import add_serve_parser, run_serve
    add_serve_parser(subparsers)          # adds the "serve" sub-command
    ...
    if args.command == "serve": return run_serve(args)

Flags mirror the settings (``--max-batch-size`` <-> ``SHADOWCORR_MAX_BATCH_SIZE``); a flag
given on the command line overrides the environment, an absent flag leaves it alone.
The bearer token has no flag (command lines are visible to every local user via ``ps``):
use ``SHADOWCORR_AUTH_TOKEN`` or ``--auth-token-file``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

if TYPE_CHECKING:
    from .settings import ServiceSettings

__all__ = ["add_serve_parser", "build_parser", "run_serve", "settings_from_args", "main"]

_NO_FLAG = {"auth_token"}


def _add_arguments(p: argparse.ArgumentParser) -> None:
    from .settings import ServiceSettings  # pydantic-settings: loaded only when `serve` is parsed

    for name, field in ServiceSettings.model_fields.items():
        if name in _NO_FLAG:
            continue
        flag = "--" + name.replace("_", "-")
        help_text = f"{field.description or name} (env SHADOWCORR_{name.upper()}, default {field.default!r})"
        if name == "model_path":
            p.add_argument("--model", flag, dest=name, default=None, metavar="PATH", help=help_text)
        else:
            # Strings go to pydantic as-is, so flags and env vars are validated by the same rules.
            p.add_argument(flag, dest=name, default=None, metavar=_metavar(name), help=help_text)
    p.add_argument(
        "--auth-token-file",
        default=None,
        metavar="PATH",
        help="read the bearer token from this file (env SHADOWCORR_AUTH_TOKEN also works; default: no auth)",
    )


def _metavar(name: str) -> str:
    if name.endswith("_s"):
        return "SECONDS"
    if name.endswith("_ms"):
        return "MS"
    if name.endswith("_bytes"):
        return "BYTES"
    return {"host": "HOST", "device": "DEVICE", "log_level": "LEVEL", "allow_no_auth": "BOOL",
            "maps_dir": "DIR"}.get(name, "N")


def add_serve_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Add the ``serve`` sub-command to an argparse ``subparsers`` object; returns its parser."""
    # `populate`: the flags come from the settings model, so they are added the first time
    # `serve` is parsed or its help shown -- `shadowcorr --help` never loads pydantic-settings.
    p = subparsers.add_parser(
        "serve",
        help="run the HTTP inference service",
        description="Run the ShadowCorr HTTP service (POST /correspond, GET /health, /info, /metrics).",
        populate=_add_arguments,
    )
    p.set_defaults(func=run_serve)
    return p


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m shadowcorr_service", description="Run the ShadowCorr HTTP service.")
    _add_arguments(p)
    return p


def settings_from_args(args: argparse.Namespace) -> "ServiceSettings":
    """Environment settings with the flags that were given laid over them."""
    from .settings import ServiceSettings

    overrides = {
        name: getattr(args, name)
        for name in ServiceSettings.model_fields
        if name not in _NO_FLAG and getattr(args, name, None) is not None
    }
    token_file = getattr(args, "auth_token_file", None)
    if token_file:
        overrides["auth_token"] = Path(token_file).read_text().strip()
    return ServiceSettings(**overrides)


def run_serve(args: argparse.Namespace) -> int:
    """Entry point of ``shadowcorr serve``; returns the exit status."""
    from pydantic import ValidationError

    from .server import serve

    try:
        settings = settings_from_args(args)
    except ValidationError as e:
        for err in e.errors(include_url=False):
            loc = ".".join(str(x) for x in err["loc"])
            if loc:
                print(f"shadowcorr serve: invalid setting {loc}: {err['msg']}", file=sys.stderr)
            else:  # a rule over several settings: its message names them
                print(f"shadowcorr serve: {err['msg'].removeprefix('Value error, ')}", file=sys.stderr)
        return 2
    except OSError as e:
        print(f"shadowcorr serve: cannot read the token file: {e}", file=sys.stderr)
        return 2
    serve(settings)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    return run_serve(build_parser().parse_args(argv))
