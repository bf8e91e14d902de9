"""The docs a newcomer reads are generated from, or checked against, the code."""
from __future__ import annotations

import contextlib
import io
import re
import shlex
from pathlib import Path
from typing import get_args

import pytest

from schemas import keys
from services.tools.launcher.cli import build_parser
from schemas.messages import FaultKind
from services.tools.launcher.params_cmd import render
from services.simulator import scenario
from tests.conftest import REPO


def test_parameters_doc_matches_the_code():
    assert render(list(keys.SERVICES)) in (REPO / "docs/parameters.md").read_text(), \
        "docs/parameters.md is stale: regenerate it from `falconry params`"


def test_scenario_doc_carries_the_loader_reference():
    assert scenario.__doc__.strip("\n") in (REPO / "docs/scenarios.md").read_text()


def test_the_scenario_docs_fault_examples_load(tmp_path):
    """The `[[faults]]` example of docs/scenarios.md, added to a shipped scenario, is one the loader
    takes (it once showed a `slow` delay the loader refuses)."""
    examples = re.findall(r"```toml\n(.*?)```", (REPO / "docs/scenarios.md").read_text(), re.S)
    faults = [block for block in examples if "[[faults]]" in block]
    assert faults
    base = (REPO / "services/simulator/scenarios/mbzirc.toml").read_text()
    for k, block in enumerate(faults):
        path = tmp_path / f"example{k}.toml"
        path.write_text(base + "\n" + block)
        assert len(scenario.load_scenario(str(path)).faults) >= block.count("[[faults]]")


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


def documented_commands(path: Path) -> list[list[str]]:
    """Every `falconry ...` command in the file's shell code blocks, continuation lines joined."""
    commands = []
    for block in re.findall(r"```sh\n(.*?)```", path.read_text(), re.S):
        for line in block.replace("\\\n", " ").splitlines():
            lexer = shlex.shlex(line.replace("$service", "tracker"), posix=True, punctuation_chars=True)
            lexer.whitespace_split = True
            lexer.commenters = "#"
            words: list[str] = []
            for token in [*lexer, ";"]:  # shell operators (&&, ;, |, &, >) end a command
                if token and set(token) <= set("&;|<>()"):
                    # `falconry ...`, or a path to it behind runuser/env
                    start = next((i for i, w in enumerate(words) if w.endswith("bin/falconry")),
                                 0 if words[:1] == ["falconry"] else None)
                    if start is not None:
                        commands.append(words[start + 1:])
                    words = []
                else:
                    words.append(token)
    return commands


@pytest.mark.parametrize("doc", ["docs/deploy.md", "deploy/README.md"])
def test_every_falconry_command_of_the_deployment_guides_is_valid(doc):
    """The guides are followed by people at a shell: each command line must be one the CLI
    accepts (spelling, options, values), and there must be commands to check."""
    commands = documented_commands(REPO / doc)
    assert len(commands) >= 8, commands
    for words in commands:
        stderr = io.StringIO()
        try:
            with contextlib.redirect_stderr(stderr), contextlib.redirect_stdout(io.StringIO()):
                build_parser().parse_args([w.replace("{start}", "x") for w in words])
        except SystemExit as exc:  # --version and --help exit 0
            if exc.code != 0:
                pytest.fail(f"{doc}: `falconry {' '.join(words)}` is rejected: {stderr.getvalue().strip()}")
