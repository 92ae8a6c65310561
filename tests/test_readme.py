"""README.md stays true and short: its opening commands are the ones CI runs, its Python quickstart runs, and it
keeps the limits of a page for users (at most 200 lines of at most 200 characters, no commit hashes in its prose:
history goes to docs/experiments.md)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"
MAX_LINES, MAX_LINE_CHARS = 200, 200
# A commit hash as git abbreviates it: 7 to 40 lowercase hex digits standing alone (not part of a word, a decimal
# number or a figure with thousands separators).
COMMIT_HASH = re.compile(r"(?<![\w.,])[0-9a-f]{7,40}(?![\w,]|\.\d)")


def _opening_block() -> list[str]:
    text = README.read_text()
    match = re.search(r"```bash\n(.*?)```", text, re.DOTALL)
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


def _prose(text: str) -> str:
    """The README without its fenced code blocks (commands may name a commit; prose may not)."""
    return re.sub(r"^```.*?^```[ \t]*$", "", text, flags=re.DOTALL | re.MULTILINE)


def test_readme_keeps_its_limits():
    lines = README.read_text().splitlines()
    assert len(lines) <= MAX_LINES, f"README.md has {len(lines)} lines (at most {MAX_LINES}); move history to docs/"
    long = [(number, len(line)) for number, line in enumerate(lines, 1) if len(line) > MAX_LINE_CHARS]
    assert not long, f"README.md lines over {MAX_LINE_CHARS} characters (line, length): {long}"
    hashes = COMMIT_HASH.findall(_prose(README.read_text()))
    assert not hashes, f"commit hashes in README.md's prose (docs/experiments.md keeps history): {hashes}"


def test_limit_checks_catch_what_they_are_for():
    """The hash pattern finds a hash in prose and not in a fenced block, nor dates, sizes or words."""
    text = (
        "Made by 8313681 (see commit/c1483c0) and e22ad51.\n```bash\ngit show 0151549\n```\n"
        "2026-12-05, 1,234,567 samples, 0.1234567 s, a decade, v0.1.0, ernet_default\n"
    )
    assert COMMIT_HASH.findall(_prose(text)) == ["8313681", "c1483c0", "e22ad51"]


@pytest.mark.slow
def test_readme_quickstart_runs(tmp_path, monkeypatch, capsys):
    """The quickstart as written, on a synthetic cloud (`sgjax example`), with the small primitive
    database in place of the full one (the only change). In this process, so that it shares the
    compiled Stage 1 and E-RNet with the other tests."""
    from sgjax_cli import main

    text = README.read_text()
    section = text[text.index("## Quickstart") :]
    code = re.search(r"```python\n(.*?)```", section, re.DOTALL).group(1)
    assert "sgjax.load_database()" in code
    code = code.replace("sgjax.load_database()", "sgjax.load_database(sgjax.DBConfig.small())")
    code += "\nassert fit.valid and len(cands) > 0 and plan.kind in ('evaluated', 'refined'), plan.reason\n"
    code += "print('QUICKSTART', plan.kind, len(cands))\n"
    monkeypatch.chdir(tmp_path)
    assert main(["example", "object.npy"]) == 0
    exec(compile(code, "README.md quickstart", "exec"), {"__name__": "quickstart"})
    assert "QUICKSTART" in capsys.readouterr().out
