"""The map services' Trigger answers (core/map_io/answers.py): written and read in one place."""
from __future__ import annotations

import pytest

from memgs_ros.core.map_io.answers import MapAnswer
from memgs_ros.errors import MessageError


@pytest.mark.parametrize("answer", [
    MapAnswer(9, 1234, 77),  # the mapper's finish
    MapAnswer(3, 10),  # a snapshot, the merger's publish
    MapAnswer(3, 10, ply="/run/map.ply"),  # a save without a bundle: the PLY first
    MapAnswer(3, 10, ply="/home/a pilot/run/map.ply", bundle="/home/a pilot/run/maps/map-20261203-010203"),
])
def test_an_answer_reads_back_as_written(answer: MapAnswer) -> None:
    assert MapAnswer.parse(answer.message()) == answer


def test_the_saved_file_comes_first() -> None:
    """A user reads the save's answer as "where is my map": the bundle, else the PLY."""
    assert MapAnswer(3, 10, ply="/r/map.ply", bundle="/r/maps/m").message().split()[0] == "/r/maps/m"
    assert MapAnswer(3, 10, ply="/r/map.ply").message() == "/r/map.ply gaussians=10 seq=3"


@pytest.mark.parametrize("text", ["no map received yet", "gaussians=3", "seq=x gaussians=3", "'unclosed seq=1"])
def test_an_answer_without_its_numbers_is_refused_naming_it(text: str) -> None:
    with pytest.raises(MessageError, match="map answer"):
        MapAnswer.parse(text)
