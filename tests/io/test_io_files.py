"""Ground-floor helpers for outputs: standard JSON, pairs of files written all or none, output
folders checked before the work, unique output names, and the memory check for sizes."""

from __future__ import annotations

import errno
import json
import math

import pytest

from geco_guide.io import devices, files
from geco_guide.io.files import (
    WriteError,
    check_output_dir,
    json_ready,
    unique_names,
    write_json_atomic,
    write_texts_atomic,
)


def test_json_is_standard_with_non_finite_values_as_null(tmp_path):
    data = {"a": math.nan, "b": [1.0, math.inf, -math.inf], "c": {"d": 2.5, "e": (math.nan,)}, "f": "x"}
    assert json_ready(data) == {"a": None, "b": [1.0, None, None], "c": {"d": 2.5, "e": [None]}, "f": "x"}
    path = write_json_atomic(tmp_path / "r.json", data)
    assert "NaN" not in path.read_text() and "Infinity" not in path.read_text()
    assert json.loads(path.read_text())["b"] == [1.0, None, None]


def test_files_written_together_appear_together_or_not_at_all(tmp_path, monkeypatch):
    a, b = tmp_path / "r.json", tmp_path / "r.md"
    assert write_texts_atomic({a: "{}\n", b: "# r\n"}) == [a, b]
    assert a.read_text() == "{}\n" and b.read_text() == "# r\n"
    calls = []

    def full_on_second(fd):
        calls.append(fd)
        if len(calls) == 2:
            raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(files.os, "fsync", full_on_second)
    with pytest.raises(WriteError, match="r.md.*No space left"):
        write_texts_atomic({a: "new json", b: "new md"})
    assert a.read_text() == "{}\n" and b.read_text() == "# r\n"  # the old pair, untouched
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.json", "r.md"]  # no temporaries


def test_output_folders_are_checked_before_the_work(tmp_path):
    assert check_output_dir(tmp_path / "new" / "deep").is_dir()
    (tmp_path / "a-file").write_text("")
    with pytest.raises(WriteError, match=r"--out '.*a-file' is a file"):
        check_output_dir(tmp_path / "a-file")
    with pytest.raises(WriteError, match="cannot write to --where"):
        check_output_dir(tmp_path / "a-file" / "below", option="--where")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a-file", "new"]  # the probe is gone


def test_unique_names_number_repeats_without_reusing_a_name():
    assert unique_names(["a", "b", "a", "a"]) == ["a", "b", "a-2", "a-3"]
    assert unique_names(["a", "a", "a-2"]) == ["a", "a-3", "a-2"]


def test_memory_check_refuses_what_cannot_fit(monkeypatch):
    assert devices.memory_limit("cpu") > 2**26  # this machine's RAM, read from the system
    monkeypatch.setattr(devices, "memory_limit", lambda device: 2**30)
    devices.check_memory_fits(2**29, "cpu", "half of it")
    with pytest.raises(ValueError, match=r"--size 9 9 9 needs at least 2 GiB of memory, more than the 1 GiB of RAM"):
        devices.check_memory_fits(2**31, "cpu", "--size 9 9 9")
    monkeypatch.setattr(devices, "memory_limit", lambda device: None)
    devices.check_memory_fits(2**80, "cpu", "anything")  # an unknown limit checks nothing
