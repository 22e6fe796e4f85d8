"""Every parameter does something: each field of every node's config classes is read as an
attribute somewhere in memgs_ros/. (Two were not: ``tracker.max_reprojection_px`` and
``tracker.keyframe_min_new_points`` were declared, ranged and documented while constants did their
job, so setting them changed no run.)"""
from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import memgs_ros
from memgs_ros.nodes.params import NODE_CONFIGS

PACKAGE = Path(memgs_ros.__file__).parent


def test_every_config_field_is_read_somewhere() -> None:
    text = "\n".join(p.read_text() for p in PACKAGE.rglob("*.py"))
    classes = {cls for configs in NODE_CONFIGS.values() for _, cls in configs}
    assert len(classes) >= 10
    unread = sorted(f"{cls.__name__}.{f.name}" for cls in classes for f in dataclasses.fields(cls)
                    if not re.search(r"\.\b" + re.escape(f.name) + r"\b", text))
    assert unread == [], f"parameters nothing reads (a constant does their job, or nothing): {unread}"
