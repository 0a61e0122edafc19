"""Starting the viser server: the bind address and port, the URL to open, and the missing-extra error."""

from __future__ import annotations

import socket

from .extra import require_viser

__all__ = ["start_server", "page_url"]


def page_url(host: str, port: int) -> str:
    """The URL a browser opens for a server bound to ``host``:``port`` (``0.0.0.0``/``::``: this machine's name,
    reachable from others; through an SSH tunnel open http://localhost:<port>)."""
    shown = socket.gethostname() if host in ("0.0.0.0", "::", "") else host
    return f"http://{shown}:{port}"


def start_server(host: str = "127.0.0.1", port: int = 8080, label: str = "tocabi-torchrl"):
    """A running ``viser.ViserServer`` on ``host``:``port`` (raises :class:`~.extra.ViewerUnavailable` without the
    extra). viser moves to the next free port when ``port`` is taken: the port it got is ``server.get_port()``."""
    viser = require_viser()
    server = viser.ViserServer(host=host, port=port, label=label, verbose=False)
    server.gui.configure_theme(control_width="large", show_share_button=False)
    return server
