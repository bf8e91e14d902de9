"""docs/cli.md is the command line's reference, generated from its parser; README.md stays short
enough to read (no table cell of reference text)."""
from __future__ import annotations

import argparse
import re

from services.tools.launcher import cli_docs
from services.tools.launcher.cli import build_parser, subcommand_parsers
from tests.conftest import REPO

CLI_DOC = REPO / "docs" / "cli.md"
README_CELL_LIMIT = 200


def test_cli_doc_is_what_the_generator_writes():
    assert CLI_DOC.read_text() == cli_docs.render(), \
        "docs/cli.md is stale: `python -m services.tools.launcher.cli_docs > docs/cli.md`"


def test_the_generator_check_flag_sees_a_stale_page(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(cli_docs, "DOC", tmp_path / "cli.md")
    assert cli_docs.main(["--check"]) == 1
    assert "stale" in capsys.readouterr().err
    assert cli_docs.main(["--write"]) == 0
    assert cli_docs.main(["--check"]) == 0


def _sections(text: str) -> dict[str, str]:
    """'falconry sim' -> the text of its `## falconry sim` section."""
    parts = re.split(r"^## (.+)$", text, flags=re.M)
    return {heading.strip(): body for heading, body in zip(parts[1::2], parts[2::2])}


def test_every_command_and_option_of_the_parser_is_in_the_cli_doc():
    """Independently of the generator: each command and sub-command has its section, and each of
    its option strings is written there in code (`--seed`, `--seed SEED`)."""
    sections = _sections(CLI_DOC.read_text())
    parser = build_parser()
    missing = []
    for command in [parser, *subcommand_parsers(parser)]:
        section = sections.get(command.prog)
        if section is None:
            missing.append(f"no section `## {command.prog}`")
            continue
        for action in command._actions:
            if isinstance(action, argparse._SubParsersAction):
                missing += [f"no section `## {command.prog} {name}`" for name in action.choices
                            if f"{command.prog} {name}" not in sections]
            for option in action.option_strings:
                if not re.search(rf"`{re.escape(option)}[ `]", section):
                    missing.append(f"{command.prog}: {option}")
    assert not missing, missing


def _table_cells(markdown: str) -> list[str]:
    """The cells of every Markdown table row outside code blocks (`\\|` is a pipe inside a cell)."""
    cells, fenced = [], False
    for line in markdown.splitlines():
        if line.lstrip().startswith("```"):
            fenced = not fenced
            continue
        if fenced or not line.lstrip().startswith("|"):
            continue
        row = line.strip().removeprefix("|").removesuffix("|")
        cells += [cell.strip() for cell in re.split(r"(?<!\\)\|", row)]
    return cells


def test_readme_table_cells_are_short():
    """Reference text (a command's every option, a service's every feature) belongs in docs/;
    a README table says one thing per cell."""
    cells = _table_cells((REPO / "README.md").read_text())
    assert cells, "README.md has no table (its fault table and catalogue are tested elsewhere)"
    long = [cell[:80] + "..." for cell in cells if len(cell) >= README_CELL_LIMIT]
    assert not long, f"README.md table cells of {README_CELL_LIMIT} characters or more: {long}"


def test_table_cells_are_split_as_markdown_does():
    assert _table_cells("| a | `x\\|y` |\n|---|---|\n```\n| not | a table |\n```\n") == ["a", "`x\\|y`", "---", "---"]
