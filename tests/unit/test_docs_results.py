"""Every table rendered into README.md and docs/*.md equals its rendering from the result file
it names (docs/results/), every result file names the command, revision, machine and date
behind it, and the README's reproduction table is what `afbl reproduce` prints."""

from __future__ import annotations

import importlib.util
import json
import math
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
_spec = importlib.util.spec_from_file_location("docs_results", ROOT / "docs" / "results.py")
results = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(results)

RESULT_FILES = sorted(results.RESULTS.glob("*.json"))
MARKDOWN = results.markdown_files()


def _blocks(path: Path) -> list[re.Match]:
    return list(results.BLOCK.finditer(path.read_text()))


def test_result_files_found_and_rendered():
    assert RESULT_FILES, "no result files in docs/results/"
    used = {m["file"] for p in MARKDOWN for m in _blocks(p) if m["file"]}
    assert {"reproduce.json", "bench_cpu.json"} <= used
    assert not used - {p.name for p in RESULT_FILES}, "a page names a missing result file"


@pytest.mark.parametrize("path", RESULT_FILES, ids=[p.name for p in RESULT_FILES])
def test_result_file_names_its_command_and_provenance(path):
    doc = json.loads(path.read_text())
    for key in results.PROVENANCE_KEYS:
        assert str(doc.get("provenance", {}).get(key, "")).strip(), f"{path.name}: no {key}"
    words = doc["provenance"]["command"].split()
    if words[0] == "env":  # environment settings stated before the command
        words = [w for w in words[1:] if "=" not in w]
    assert words[0] in ("afbl", "python"), path.name
    # a recorded command's output and files, or a measurement script's summary
    assert doc.get("files") or doc.get("stdout") or doc.get("summary"), (
        f"{path.name} holds no result"
    )
    results.load(path.name)  # the loader's own check agrees


@pytest.mark.parametrize("path", MARKDOWN, ids=[str(p.relative_to(ROOT)) for p in MARKDOWN])
def test_rendered_blocks_equal_their_files(path):
    """A block edited by hand, or a result file changed without `python docs/results.py render`,
    fails here."""
    for m in _blocks(path):
        expected = results.render_block(m["kind"], m["file"])
        assert m["body"] == expected + "\n", (
            f"{path.relative_to(ROOT)}: the '{m['kind']} {m['file'] or ''}' block differs from "
            "its rendering; run `python docs/results.py render`"
        )


def test_the_check_catches_a_changed_number(tmp_path):
    """The comparison above fails on a table whose digit was changed."""
    text = (ROOT / "README.md").read_text()
    changed = text.replace("2.8358e-03", "2.8359e-03", 1)
    assert changed != text and results.render_text(changed) != changed
    assert results.render_text(text) == text


def test_a_result_file_without_command_is_refused(tmp_path, monkeypatch):
    doc = json.loads((results.RESULTS / "reproduce.json").read_text())
    doc["provenance"]["command"] = ""
    (tmp_path / "x.json").write_text(json.dumps(doc))
    monkeypatch.setattr(results, "RESULTS", tmp_path)
    with pytest.raises(ValueError, match="command"):
        results.load("x.json")


def test_readme_table_is_what_afbl_reproduce_printed():
    """The README's reproduction table equals, digit for digit, the table in the recorded
    standard output of `afbl reproduce --out results/paper`."""
    doc = results.load("reproduce.json")
    assert doc["provenance"]["command"] == "afbl reproduce --out results/paper"
    (block,) = [m for m in _blocks(ROOT / "README.md") if m["kind"] == "reproduce-table"]
    table = block["body"].split("```\n")[1].split("\n```")[0]
    assert table.startswith("ISE over 0-20 s") and "uncertain_sine" in table
    assert table + "\n" in doc["stdout"]


def test_readme_commands_as_written():
    """The README's two commands and CI's test command."""
    readme = (ROOT / "README.md").read_text()
    assert "```bash\npip install -e . && afbl reproduce --out results/paper\n```" in readme
    assert '```bash\npip install -e ".[test]" && python -m pytest\n```' in readme
    assert "\npython -m pytest\n" in (ROOT / ".ci" / "run").read_text()
    assert len(readme.splitlines()) <= 250


def test_distribution_reference_names_every_key():
    from afbl_jax.studies.montecarlo import DEFAULT_DISTRIBUTION

    page = results.distribution_reference()
    for section, keys in DEFAULT_DISTRIBUTION.items():
        assert f"`[{section}]`" in page
        for key in keys:
            assert f"| `{key}` |" in page, (section, key)


@pytest.mark.slow
def test_reproduce_json_is_current(tmp_path):
    """`afbl reproduce` run now gives the numbers of docs/results/reproduce.json (ISE of order
    1e-13 is integration round-off and may differ on another CPU: compared to 1e-9)."""
    r = subprocess.run(
        [sys.executable, "-c", "import sys; from afbl_jax.cli import main; sys.exit(main())"]
        + ["reproduce", "--out", str(tmp_path), "--no-figures"],
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    now = json.loads((tmp_path / "ise.json").read_text())
    (kept,) = results.load("reproduce.json")["files"].values()
    for key, per in kept.items():
        if key == "meta":
            continue
        for name, vals in per.items():
            for metric, v in vals.items():
                assert math.isclose(now[key][name][metric], v, rel_tol=1e-6, abs_tol=1e-9)
