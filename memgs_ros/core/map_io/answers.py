"""What the map services answer, typed: the mapper's ``memgs/mapper/finish`` and snapshot request,
the merger's ``memgs/save_map`` and ``memgs/publish_map`` reply in a std_srvs/Trigger's message, as
one line written and read here alone: the saved file first where there is one (a map bundle, else
the PLY: a user reads the answer as "where is my map"), then ``key=value`` words.

    /run/maps/map-20261203-010203 ply=/run/map.ply gaussians=21207 seq=40 epoch=7
"""
from __future__ import annotations

import shlex
from dataclasses import dataclass

from memgs_ros.errors import MessageError


@dataclass(frozen=True)
class MapAnswer:
    """seq: the map's last delta seq (the closing snapshot's after a finish); gaussians: its size;
    epoch: the delta epoch (the mapper's answers); ply / bundle: where the merger saved it."""

    seq: int
    gaussians: int
    epoch: int | None = None
    ply: str | None = None
    bundle: str | None = None

    def message(self) -> str:
        first = self.bundle or self.ply
        words = [shlex.quote(first)] if first else []
        if self.bundle and self.ply:
            words.append(f"ply={shlex.quote(self.ply)}")
        words += [f"gaussians={self.gaussians}", f"seq={self.seq}"]
        if self.epoch is not None:
            words.append(f"epoch={self.epoch}")
        return " ".join(words)

    @classmethod
    def parse(cls, text: str) -> MapAnswer:
        """The answer in ``text``; MessageError naming what is missing or not a number."""
        try:
            words = shlex.split(text)
        except ValueError as err:
            raise MessageError(f"map answer {text!r}: {err}") from err
        path = words.pop(0) if words and "=" not in words[0] else None
        kv = dict(w.split("=", 1) for w in words if "=" in w)
        try:
            seq, gaussians = int(kv["seq"]), int(kv["gaussians"])
            epoch = int(kv["epoch"]) if "epoch" in kv else None
        except (KeyError, ValueError) as err:
            raise MessageError(f"map answer {text!r} lacks a number for {err}") from err
        ply = kv.get("ply", path)
        return cls(seq, gaussians, epoch, ply, path if "ply" in kv else None)
