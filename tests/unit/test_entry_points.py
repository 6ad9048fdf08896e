"""The entry points: ``cosim5g`` and the federate process are the only ones in the packages; every
developer script in tools/ calls its module's ``main`` and is listed in tools/README.md."""

from __future__ import annotations

import ast
import importlib.util
import tomllib
from pathlib import Path

import pytest

from interfaces.cli import main

ROOT = Path(__file__).parents[2]
TOOLS = sorted((ROOT / "tools").glob("*.py"))


def _is_main_block(node: ast.stmt) -> bool:
    return (isinstance(node, ast.If) and isinstance(node.test, ast.Compare)
            and isinstance(node.test.left, ast.Name) and node.test.left.id == "__name__")


def test_only_the_cli_and_the_federate_process_have_a_main_block() -> None:
    find = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"]["find"]
    with_main = set()
    for package in {p.rstrip("*") for p in find["include"]}:
        for path in (ROOT / package).rglob("*.py"):
            if any(_is_main_block(node) for node in ast.parse(path.read_text()).body):
                with_main.add(path.relative_to(ROOT).as_posix())
    assert with_main == {"interfaces/cli.py", "services/main.py"}, "a command goes to cli.py or tools/"


@pytest.mark.parametrize("tool", TOOLS, ids=[t.name for t in TOOLS])
def test_a_tool_calls_the_main_of_its_module_and_is_listed(tool: Path) -> None:
    tree = ast.parse(tool.read_text())
    assert ast.get_docstring(tree), f"{tool.name}: no docstring"
    (module,) = [n.module or "" for n in tree.body if isinstance(n, ast.ImportFrom)
                 and [a.name for a in n.names] == ["main"]]
    spec = importlib.util.find_spec(module)
    assert spec is not None and spec.origin is not None, module
    defined = {n.name for n in ast.parse(Path(spec.origin).read_text()).body if isinstance(n, ast.FunctionDef)}
    assert "main" in defined, f"{module} has no main(argv)"
    assert f"`{tool.name}" in (ROOT / "tools" / "README.md").read_text(), f"{tool.name} not in tools/README.md"


@pytest.mark.parametrize("command", ["netsim", "calibrate"])
def test_a_subcommand_with_its_own_parser_gets_every_argument(command: str,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as done:
        main([command, "--help"])
    assert done.value.code == 0
    assert capsys.readouterr().out.startswith(f"usage: cosim5g {command} ")
