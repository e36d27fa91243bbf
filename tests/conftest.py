"""Shared test fixtures: the VGGT / UFM parity fixtures (spec section 7), shipped in tests/fixtures/,
and the tiny random estimators, built once for the session.

The tests mirror the package's folders (tests/sampler/ tests geco_guide/sampler/, ...); the
top-level modules' tests sit here.

Tiny configurations, state dicts under upstream key names, inputs and reference outputs, kept in
the repository so that every clone runs the parity tests; ``test_parity_fixtures_are_the_reference_files``
notices a fixture changed by accident. Every test sees the package's log lines on stderr, as a
command shows them (:func:`command_logs`).
"""

from __future__ import annotations

import logging
from pathlib import Path

import pytest
import torch

from geco_guide.io.logs import log_to_stderr

FIXTURES = Path(__file__).resolve().parent / "fixtures"


def load_parity_fixture(name: str) -> dict:
    """``tests/fixtures/<name>.pt`` (a dict; see the spec's section 7 for its layout)."""
    return torch.load(FIXTURES / f"{name}.pt", weights_only=False)


@pytest.fixture(scope="session")
def vggt_fixture() -> dict:
    return load_parity_fixture("vggt_tiny")


@pytest.fixture(scope="session")
def ufm_fixture() -> dict:
    return load_parity_fixture("ufm_tiny")


@pytest.fixture(scope="session")
def estimators():
    """The tiny random VGGT and UFM (seed 0) as one :class:`~geco_guide.estimators.Estimators`,
    built once for the session; frozen, so the tests that share them cannot change them."""
    from geco_guide.tiny import tiny_estimators

    return tiny_estimators(0)


@pytest.fixture
def no_loading(monkeypatch):
    """A run that gets as far as loading its models fails the test: for refusals that must come
    before anything loads."""
    from geco_guide import generation

    def refuse(*args, **kwargs):
        raise AssertionError("the models loaded")

    monkeypatch.setattr(generation, "load_models", refuse)


@pytest.fixture
def stub_generation(monkeypatch):
    """Stands in for loading and sampling in :mod:`geco_guide.generation`: call it with the
    ``[1, F, 3, H, W]`` frames the run's video is made of; the rest of the path (checks, sidecar,
    writing) is the real one."""
    from types import SimpleNamespace

    from geco_guide import generation
    from geco_guide.families import model_named
    from geco_guide.sampler.running.context import GuidanceReport
    from geco_guide.sampler.pipelines.loading import LoadedPipeline

    def stub(frames):
        pipe = SimpleNamespace(device=frames.device)
        monkeypatch.setattr(generation, "load_models", lambda cfg, estimators=True: generation.Models(
            LoadedPipeline(pipe, model_named(cfg.model.name), "stub"), None))
        monkeypatch.setattr(generation, "sample", lambda models, cfg, prompt, **kwargs: generation.Sample(
            frames, GuidanceReport(scheduler="stub"), 0.0))

    return stub


def pytest_collection_modifyitems(config, items):
    """The slow end-to-end tests run last: a failure of the quick ones shows first."""
    items.sort(key=lambda item: item.get_closest_marker("slow") is not None)


@pytest.fixture(autouse=True)
def command_logs():
    """The package's log lines on stderr, as every command shows them (:func:`log_to_stderr`),
    and taken away after each test: a command run in-process leaves its handler to no other test."""
    package = logging.getLogger("geco_guide")
    level = package.level
    handler = log_to_stderr()
    yield
    package.removeHandler(handler)
    package.setLevel(level)
