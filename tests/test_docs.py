"""The docs a newcomer reads are generated from, or checked against, the code."""
from __future__ import annotations

from typing import get_args

from schemas import keys
from schemas.messages import FaultKind
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


def test_readme_says_what_each_fault_does_and_what_the_team_does_about_it():
    readme = (REPO / "README.md").read_text()
    table = readme[readme.index("| fault | the faulted UAV | its partners |"):].split("\n\n")[0]
    first_cells = " ".join(row.split("|")[1] for row in table.splitlines()[2:])
    missing = [kind for kind in get_args(FaultKind) if f"`{kind}`" not in first_cells]
    assert not missing, f"README's fault table has no row for {missing}"
