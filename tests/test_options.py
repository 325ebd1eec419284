"""``logpipe.options``: command options as the API takes them → the values the stages take, and one-line errors
that name the option and the bad value."""

from __future__ import annotations

from pathlib import Path

import pytest

from logpipe.errors import LogpipeError
from logpipe.options import as_paths, gates, map_files, names


def test_key_value_options_parse_and_name_the_bad_item() -> None:
    assert map_files(["MIA=a/b.npz", "PIT=c=d.npz"]) == {"MIA": Path("a/b.npz"), "PIT": Path("c=d.npz")}
    assert map_files({"MIA": "x.npz"}) == {"MIA": Path("x.npz")}
    assert gates(["k6.minFDE=2.5", " k1.ade =0.6"]) == {"k6.minFDE": 2.5, "k1.ade": 0.6}
    with pytest.raises(LogpipeError, match=r"--map expects MAP_ID=FILE, got 'MIA'"):
        map_files(["MIA"])
    with pytest.raises(LogpipeError, match=r"--fail-above 'k1.ade': expected kN.METRIC=NUMBER"):
        gates(["k1.ade"])
    with pytest.raises(LogpipeError, match=r"--fail-above 'k1.ade=abc': expected"):
        gates(["k1.ade=abc"])


def test_names_and_paths_accept_one_or_many() -> None:
    assert names("vehicle, bus_truck,") == ("vehicle", "bus_truck")
    assert names(["a", " b "]) == ("a", "b")
    assert names(None) is None
    assert as_paths("one/path") == [Path("one/path")]
    assert as_paths(["a", Path("b")]) == [Path("a"), Path("b")]
    assert as_paths(None) == []
