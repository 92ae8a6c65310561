"""README.md stays true: its opening commands are the ones CI runs, and its Python quickstart runs."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"


def _opening_block() -> list[str]:
    text = README.read_text()
    match = re.search(r"```bash\n(.*?)```", text, re.S)
    assert match and text.index(match.group(0)) < 40, "README must open with its bash block"
    return match.group(1).strip().splitlines()


def test_readme_opens_with_venv_install_main_job_and_tests():
    lines = _opening_block()
    tags = [line.rsplit("#", 1)[1].split()[0] for line in lines]
    assert tags == ["venv", "install", "main", "tests"], tags
    assert "python -m venv" in lines[0] and 'pip install -e ".[test]"' in lines[1]
    assert lines[2].startswith("sgjax declutter") and "python -m pytest" in lines[3]
    # CI reads the same lines (.ci/run's readme_command) and runs them.
    ci = (README.parent / ".ci" / "run").read_text()
    assert "readme_command install" in ci and "readme_command tests" in ci and "lint-imports" in ci


@pytest.mark.slow
def test_readme_quickstart_runs(tmp_path, monkeypatch, capsys):
    """The quickstart as written, on a synthetic cloud (`sgjax example`), with the small primitive
    database in place of the full one (the only change). In this process, so that it shares the
    compiled Stage 1 and E-RNet with the other tests."""
    from sgjax_cli import main

    text = README.read_text()
    section = text[text.index("## Quickstart") :]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    assert "sgjax.load_database()" in code
    code = code.replace("sgjax.load_database()", "sgjax.load_database(sgjax.DBConfig.small())")
    code += "\nassert fit.valid and len(cands) > 0 and plan.kind in ('evaluated', 'refined'), plan.reason\n"
    code += "print('QUICKSTART', plan.kind, len(cands))\n"
    monkeypatch.chdir(tmp_path)
    assert main(["example", "object.npy"]) == 0
    exec(compile(code, "README.md quickstart", "exec"), {"__name__": "quickstart"})
    assert "QUICKSTART" in capsys.readouterr().out
