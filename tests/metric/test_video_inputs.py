"""The inputs of a scoring run: paths made videos with unique names, what each writes, and the
checks made before any model loads."""

from __future__ import annotations

from pathlib import Path

import pytest

from geco_guide.metric.video_inputs import check_inputs_and_outputs, check_scorable, expand_inputs, run_outputs


def _video(path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"not decoded here")
    return path


def test_inputs_of_one_stem_get_unique_names_and_a_missing_one_its_error(tmp_path):
    a, b = _video(tmp_path / "a" / "clip.mp4"), _video(tmp_path / "b" / "clip.mp4")
    items = expand_inputs([str(a), str(b), str(tmp_path / "none.mp4")])
    assert [item.name for item in items] == ["clip", "clip-2", "none"]
    assert [item.error for item in items] == [None, None, "no such file or folder"]


def test_nothing_scorable_is_one_line_naming_each_input(tmp_path):
    items = expand_inputs([str(tmp_path / "x.mp4"), str(tmp_path)])
    with pytest.raises(ValueError) as err:
        check_scorable(items)
    assert "\n" not in str(err.value) and "x.mp4: no such file or folder" in str(err.value)
    assert "holds no video" in str(err.value)


def test_an_existing_output_is_refused_unless_overwrite(tmp_path):
    items = expand_inputs([str(_video(tmp_path / "in" / "clip.mp4"))])
    out = tmp_path / "out"
    out.mkdir()
    assert run_outputs(items, out, True, False, True) == [out / "clip.geco.json", out / "clip.maps.mp4",
                                                          out / "geco_scores.csv", out / "geco_summary.json"]
    (out / "clip.maps.mp4").write_bytes(b"")
    check_inputs_and_outputs(items, out, overwrite=False, maps=False, detection=False)  # the maps are not written
    with pytest.raises(ValueError, match="clip.maps.mp4' already exists .* pass --overwrite"):
        check_inputs_and_outputs(items, out, overwrite=False, maps=True, detection=False)
    check_inputs_and_outputs(items, out, overwrite=True, maps=True, detection=False)
