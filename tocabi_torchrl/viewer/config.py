"""``ViewerConfig``: the live web viewer's options (the run config's ``viewer`` section). Standard library only, so
the config tree loads without the ``viewer`` extra installed."""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["ViewerConfig", "MAX_STREAM_WORLDS", "MAX_SHOWN", "expand_viewer_flag"]

#: At most this many training worlds are copied to the host for the viewer (the issue's bound: 64 robots drawn at
#: 30 fps cost ~65 KB a copy; more would crowd the page without showing anything new).
MAX_STREAM_WORLDS = 64
#: The most robots a policy's page draws (the first worlds; the simulation may run more): a checkpoint's
#: (``play.py --viewer``) and an exported policy's (``sim2sim.py --viewer``) alike.
MAX_SHOWN = 256


@dataclass
class ViewerConfig:
    """Stream a few training worlds to a web page (viser) while training runs (``recipes/ppo_walk.py --viewer``).

    ``host``/``port``: where the page is served (``127.0.0.1``: this machine only, reach a remote one through
    ``ssh -L 8080:localhost:8080``; ``0.0.0.0``: every interface). ``worlds``: how many of the training worlds are
    shown (the first ones, at most :data:`MAX_STREAM_WORLDS`). ``every``: policy steps between two host copies of
    their body poses (a copy still in flight is never waited for: that tick is skipped).
    """

    enabled: bool = False
    """serve a live web page of a few training worlds while training (the viewer extra; docs/viewer.md)"""
    host: str = "127.0.0.1"
    """address the page is served on (127.0.0.1: this machine, reach it via ssh -L; 0.0.0.0: every interface)"""
    port: int = 8080
    """TCP port of the page"""
    worlds: int = 16
    """training worlds shown (the first ones; at most 64)"""
    every: int = 8
    """policy steps between two host copies of the shown worlds' body poses"""

    def validate(self) -> None:
        """Raise ``ValueError`` naming the bad option (by its path) and what it accepts."""
        if not isinstance(self.port, int) or not 0 <= self.port <= 65535:
            raise ValueError(f"viewer.port is {self.port!r}: give a TCP port in [0, 65535] (0: any free one)")
        if not isinstance(self.worlds, int) or not 1 <= self.worlds <= MAX_STREAM_WORLDS:
            raise ValueError(f"viewer.worlds is {self.worlds!r}: show between 1 and {MAX_STREAM_WORLDS} worlds")
        if not isinstance(self.every, int) or self.every < 1:
            raise ValueError(f"viewer.every is {self.every!r}: give the policy steps between copies, at least 1")
        if not isinstance(self.host, str) or not self.host:
            raise ValueError(f"viewer.host is {self.host!r}: give an address to bind, e.g. 127.0.0.1 or 0.0.0.0")


def expand_viewer_flag(argv: list[str]) -> list[str]:
    """``argv`` with each bare ``--viewer`` (the recipes' shorthand) spelt as the config path ``--viewer.enabled
    true``; other arguments unchanged."""
    out: list[str] = []
    for arg in argv:
        out += ["--viewer.enabled", "true"] if arg == "--viewer" else [arg]
    return out
