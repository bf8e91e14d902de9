"""The docs a newcomer reads are generated from, or checked against, the code."""
from __future__ import annotations

from schemas import keys
from services.launcher.params_cmd import render
from services.simulator import scenario
from tests.conftest import REPO


def test_parameters_doc_matches_the_code():
    assert render(list(keys.SERVICES)) in (REPO / "docs/parameters.md").read_text(), \
        "docs/parameters.md is stale: regenerate it from `falconry params`"


def test_scenario_doc_carries_the_loader_reference():
    assert scenario.__doc__.strip("\n") in (REPO / "docs/scenarios.md").read_text()


def test_readme_names_every_service_and_command():
    readme = (REPO / "README.md").read_text()
    for service in keys.SERVICES:
        assert f"`{service}`" in readme
    for command in ("falconry sim", "falconry run", "falconry health", "falconry params", "make sim", "make test"):
        assert command in readme
