"""The package's data files (the published configs, the memory plans' estimates): no command line
reads them to answer ``--help``; a missing or damaged file is one line naming it; a model the
estimates do not know is a warning naming the plan it then gets."""

from __future__ import annotations

import json
import logging

import pytest

from geco_guide.__main__ import COMMANDS, main
from geco_guide.families import MODELS
from geco_guide.families import published
from geco_guide.families.published import PackageDataError, published_configs, traced_models
from geco_guide.sampler.running import memory_plan
from geco_guide.sampler.algorithm.config import GuidanceConfig
from geco_guide.sampler.running.run_options import RunOptions

ESTIMATES_ENTRY = {"model_ids": ["x/y"], "signature": {}, "estimates": {}, "video": {}}


@pytest.fixture
def fresh_tables():
    """The files read anew by each test (and the shipped ones again after it)."""
    published._table.cache_clear()
    memory_plan._read_estimates.cache_clear()
    yield
    published._table.cache_clear()
    memory_plan._read_estimates.cache_clear()


@pytest.mark.parametrize("argv", [["--help"], *[[name, "--help"] for name in COMMANDS],
                                  ["bench", "cost", "--help"], ["bench", "plans", "--help"]])
def test_help_reads_no_package_data(argv, monkeypatch, capsys):
    def refuse(*args):
        raise AssertionError("a package data file was read")

    monkeypatch.setattr(published, "_table", refuse)
    monkeypatch.setattr(memory_plan, "_read_estimates", refuse)
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    assert exit_.value.code == 0
    assert "usage:" in capsys.readouterr().out


def test_the_traced_models_are_those_the_published_configs_hold(fresh_tables):
    """The command lines list the traced models from the registry; the shipped file holds exactly them."""
    shipped = json.loads(published.PUBLISHED_PATH.read_text(encoding="utf-8"))["models"]
    assert traced_models() == list(shipped)
    assert set(traced_models()) | set(published.LEFT_OUT) == {n for n, m in MODELS.items() if m.generates}


@pytest.mark.parametrize("content, problem", [
    (None, "cannot be read"),
    ('{"models": {"ltx-vid', "not JSON"),
    ("{}", "no 'models' table"),
    ('{"models": {}}', "ltx-video has no entry"),
    ('{"models": {"ltx-video": {"transformer": {}}}}', "ltx-video has an entry without the key 'vae'"),
])
def test_a_missing_or_damaged_published_file_is_one_line_naming_it(content, problem, tmp_path, monkeypatch,
                                                                   fresh_tables):
    path = tmp_path / "published_configs.json"
    if content is not None:
        path.write_text(content)
    monkeypatch.setattr(published, "PUBLISHED_PATH", path)
    with pytest.raises(PackageDataError) as err:
        published_configs("ltx-video")
    message = str(err.value)
    assert "\n" not in message and str(path) in message and problem in message, message


@pytest.mark.slow  # imports the cost model
def test_bench_cost_on_a_damaged_published_file_is_one_line(tmp_path, monkeypatch, capsys, fresh_tables):
    path = tmp_path / "published_configs.json"
    path.write_text("")
    monkeypatch.setattr(published, "PUBLISHED_PATH", path)
    assert main(["bench", "cost", "--model", "ltx-video"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err, err
    assert f"the package data file {path} is damaged (not JSON" in err


@pytest.mark.parametrize("content, problem", [
    ('{"models": {"tiny": {"model_ids"', "not JSON"),
    ("{}", "no 'models' table"),
    ('{"models": {"tiny": {"model_ids": []}}}', "the entry 'tiny' lacks signature, estimates, video"),
])
def test_damaged_estimates_are_one_line_naming_the_file_before_loading(content, problem, tmp_path, monkeypatch,
                                                                      capsys, fresh_tables):
    from geco_guide import generation
    from geco_guide.cli.generate import main as generate

    def refuse(*args, **kwargs):
        raise AssertionError("the models loaded")

    path = tmp_path / "memory_plans.json"
    path.write_text(content)
    monkeypatch.setattr(memory_plan, "ESTIMATES_PATH", path)
    monkeypatch.setattr(generation, "load_models", refuse)
    code = generate(["--preset", "tiny", "--prompt", "a marble bust", "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert "\n" not in err and err.startswith("error: the package data file"), err
    assert str(path) in err and problem in err
    assert not (tmp_path / "out").exists()


def _plan(model_id: str):
    return memory_plan.plan_before_loading(GuidanceConfig(), RunOptions(), model_id, 9, 32, 48, device_gb=80.0)


def test_missing_estimates_warn_naming_the_file_and_the_plan(tmp_path, monkeypatch, caplog, fresh_tables):
    path = tmp_path / "memory_plans.json"
    monkeypatch.setattr(memory_plan, "ESTIMATES_PATH", path)
    with caplog.at_level(logging.WARNING, logger=memory_plan.__name__):
        choice = _plan("tiny-random")
    assert choice.plan is memory_plan.SAFE_PLAN
    warnings = [r.getMessage() for r in caplog.records]
    assert any(str(path) in w and "are missing" in w and "'leanest'" in w for w in warnings), warnings


def test_a_model_the_estimates_do_not_know_is_a_warning_naming_its_plan(tmp_path, monkeypatch, caplog,
                                                                       fresh_tables):
    path = tmp_path / "memory_plans.json"
    path.write_text(json.dumps({"models": {"other": ESTIMATES_ENTRY}}))
    monkeypatch.setattr(memory_plan, "ESTIMATES_PATH", path)
    with caplog.at_level(logging.WARNING, logger=memory_plan.__name__):
        choice = _plan("someone/unknown-model")
    assert choice.plan is memory_plan.SAFE_PLAN
    assert [r.getMessage() for r in caplog.records] == [
        "run.memory_plan=auto: no estimates for this model in faithful mode with decoder vae: the most memory-saving "
        "plan, 'leanest'"]


def test_a_known_model_plans_without_a_warning(caplog, fresh_tables):
    with caplog.at_level(logging.WARNING, logger=memory_plan.__name__):
        choice = _plan("tiny-random")
    assert choice.predicted_peak_gb is not None and not caplog.records
