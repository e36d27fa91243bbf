"""``geco robustness`` writes its tables beside the JSON and the plot, as ``geco validate`` does."""

from __future__ import annotations

import json

from geco_guide.bench.report import fmt
from geco_guide.bench.robustness import CUES
from geco_guide.cli import robustness


def test_the_markdown_tables_hold_every_level_of_the_json(tmp_path, capsys):
    assert robustness.main(["--out", str(tmp_path), "--size", "3", "16", "16", "--depth-sigmas", "0", "1e308",
                            "--flow-sigmas", "0.5"]) == 0
    assert f"wrote {tmp_path / 'robustness.json'}, {tmp_path / 'robustness.md'} and" in capsys.readouterr().out
    report = json.loads((tmp_path / "robustness.json").read_text())
    markdown = (tmp_path / "robustness.md").read_text()
    for noisy_input in ("depth", "flow"):
        section = markdown.split(f"## {noisy_input} noise\n\n")[1].split("\n\n")[0].splitlines()
        assert section[0] == ("| sigma | " + " | ".join(f"{task} AP {cue}" for task in ("Task 2 (warp)", "Task 3 (occlusion)")
                                                       for cue in CUES) + " | rigid clip fused |")
        rows = report[noisy_input]
        assert len(section) == 2 + len(rows["sigmas"])
        for k, line in enumerate(section[2:]):
            values = [rows[task][cue][k] for task in ("warp", "occlusion") for cue in CUES]
            cells = [fmt(v if v is not None else float("nan"), 3) for v in values]
            fused = fmt(rows["rigid_fused"][k] if rows["rigid_fused"][k] is not None else float("nan"))
            assert line == f"| {rows['sigmas'][k]:g} | " + " | ".join(cells) + f" | {fused} |"
    assert "| 1e+308 | - | - | - | - | - | - | - |" in markdown  # the overflowing level: no score
