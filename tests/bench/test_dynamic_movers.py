"""Movers with exact ground truth (a box that changes shape while it moves, a box that stretches):
the three checks of ``movers="rigid"`` on a fixed seed, and its two measures with automatic masks
on the eight drawn scenes ``geco validate --dynamic`` checks (docs/validation.md quotes them)."""

from __future__ import annotations

from pathlib import Path

import pytest
from photometric import photometric_error
from quoted_tables import same_table

from geco_guide.bench.dynamic_suite import (
    MOVER_SEEDS,
    TARGETS,
    DynamicScenes,
    drawn_movers_markdown,
    drawn_movers_validation,
    mover_clips,
    movers_validation,
)
from geco_guide.bench.synthetic import drawn_mover, moving_boxes

VALIDATION_PAGE = Path(__file__).resolve().parents[2] / "docs" / "validation.md"
DRAWN_TABLE = ("<!-- drawn mover scenes: geco validate --dynamic -->", "<!-- end of the table -->")


@pytest.fixture(scope="module")
def clips():
    return mover_clips(DynamicScenes(6, 48, 64, seed=0))


@pytest.mark.slow
def test_the_deformed_and_the_stretching_box_have_exact_flow(clips):
    for name in ("deformed_moving", "stretching"):
        clip = clips[name]
        on_box = clip.dynamic_mask[0]
        error, count = photometric_error(clip, 0, 3, on_box)
        assert count > 50 and error < 0.02, name
        # their own motion is more than the camera's: the tests below have teeth
        assert clip.residual_displacement(0, 3)[on_box].max() > 2.0, name
    deformed = clips["deformed_moving"]
    assert deformed.mask.any() and not (deformed.mask & ~deformed.dynamic_mask).any()  # on the box alone
    still = clips["deformed_still"]
    assert still.mask.any() and not (still.mask & ~still.dynamic_mask).any()  # the same warp, on the still box
    assert (clips["stretching"].dynamic_mask[-1].sum() > 1.3 * clips["stretching"].dynamic_mask[0].sum())  # parts move apart


@pytest.fixture(scope="module")
def report():
    return movers_validation(DynamicScenes(6, 48, 64, seed=0))


@pytest.mark.slow
def test_rigid_removes_what_a_rigid_mover_adds(report):
    rigid = report["rigid"]
    added = rigid["moving/none/drop"] - rigid["still/none/drop"]
    assert added > 100 * rigid["still/none/drop"]  # without a mask the box dominates
    assert rigid["removed"] >= TARGETS["movers_removed"]
    assert rigid["score_ratio"] <= TARGETS["movers_score_ratio"]
    assert [row["verdict"] for row in report["movers"]["moving/auto/rigid"]] == ["rigid"]


@pytest.mark.slow
def test_a_mover_that_changes_shape_is_found_by_rigid_and_lost_by_drop(report):
    deformed = report["deformed"]
    assert deformed["ap_ratio"] >= TARGETS["movers_ap_ratio"]
    assert deformed["moving/auto/drop"] <= 2 * deformed["chance"]  # drop: the deformation is masked away
    assert deformed["moving/true/rigid"] >= TARGETS["movers_ap_ratio"] * deformed["still/none/drop"]


@pytest.mark.slow
def test_a_non_rigid_mover_is_masked_not_scored(report):
    non_rigid = report["non_rigid"]
    assert [row["verdict"] for row in report["movers"]["stretching/true/rigid"]] == ["non-rigid"]
    assert non_rigid["true/rigid"] == non_rigid["true/drop"] < 0.01 * non_rigid["none/drop"]
    assert all(t["met"] for t in report["targets"].values()), report["targets"]


def test_drawn_movers_are_seeded_and_seed_0_is_the_sliding_box():
    assert drawn_mover(0) == moving_boxes()[0]
    assert drawn_mover(3) == drawn_mover(3) and drawn_mover(3) != drawn_mover(4)
    speeds = [sum(v * v for v in drawn_mover(seed).velocity) ** 0.5 for seed in range(1, 20)]
    assert all(0.06 <= speed <= 0.35 for speed in speeds)


@pytest.mark.slow
def test_rigid_with_automatic_masks_holds_on_every_drawn_scene():
    """What ``geco validate --dynamic`` checks, at its size, on its eight seeds (about a minute on
    one core): the false positive removed and the deformation's score recovered. Seed 4's box
    leaves the view (the masks must follow it into its unmatched pixels: before, 97 % removed and
    36x the still box) and seeds 2 and 3 show faces at a grazing angle (the target's depth must be
    read on the surface: before, seed 3's box went unmasked in five frames, 41 % removed)."""
    report = drawn_movers_validation(DynamicScenes())
    assert list(report["seeds"]) == [str(seed) for seed in range(MOVER_SEEDS)]
    for seed, row in report["seeds"].items():
        assert row["false_positive_removed"] >= TARGETS["movers_false_positive_removed"], seed
        assert row["deformation_recovered"] >= TARGETS["movers_deformation_recovered"], seed
        assert row["moving"] > 100 * row["still"], seed  # the box dominates when nothing is masked: the test has teeth
    assert all(target["met"] for target in report["targets"].values()), report["targets"]
    # docs/validation.md quotes the command's table of these scenes
    begin, end = DRAWN_TABLE
    quoted = VALIDATION_PAGE.read_text().split(begin, 1)[1].split(end, 1)[0].strip()
    assert same_table("\n".join(line for line in drawn_movers_markdown(report["seeds"]) if line.startswith("|")), quoted)
