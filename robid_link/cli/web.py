"""``robid web``: the operator's page over a config's state dir, read-only, without a daemon
(the daemon serves the same page when its config has ``web.listen``)."""

from __future__ import annotations

import argparse

from robid_link.cli.types import Command, config_option

__all__ = ["COMMANDS"]


def _web_options(p: argparse.ArgumentParser) -> None:
    config_option(p)
    p.add_argument("--listen", metavar="HOST:PORT",
                   help="address to serve (default web.listen of the config, else "
                        "127.0.0.1:8765; another than loopback needs web.tls_cert, "
                        "web.tls_key and a token)")


def _web(args: argparse.Namespace) -> int:
    from robid_link.web.command import run_web

    return run_web(args.config, args.listen)


COMMANDS = (
    Command(name="web", help="the operator's page, read-only, from a config's state dir (no "
            "daemon needed)", options=_web_options, run=_web),
)
