"""The documentation's result files: record a command's output with its provenance, and render
the tables of README.md and docs/*.md from those files.

    python docs/results.py record NAME [--keep PATH ...] [--copy PATH DEST ...] -- COMMAND ...
    python docs/results.py render            # rewrite every rendered block in place
    python docs/results.py render --check    # exit 1 if a block differs from its file

``record`` runs COMMAND in a fresh temporary folder (so a relative ``--out`` lands there), shows
and captures its standard output, and writes ``docs/results/NAME.json``::

    {"provenance": {"command", "git_revision", "machine", "date", "load_average", "wall_s"},
     "stdout": "...", "files": {PATH: <the JSON file COMMAND wrote at PATH>}}

A rendered block in a Markdown file is the text between ``<!-- render: KIND [FILE] -->`` and
``<!-- /render -->``: ``render`` replaces it by ``RENDERERS[KIND](docs/results/FILE)`` (or, for
the kinds of ``GENERATED``, by what they generate from the code), so a table is never copied
by hand. The mkdocs hook (``docs/hooks.py``) renders the pages the same way when the site is
built, and ``tests/unit/test_docs_results.py`` fails when a committed block and its file
disagree or a result file names no command.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import platform
import re
import shlex
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

DOCS = Path(__file__).resolve().parent
ROOT = DOCS.parent
RESULTS = DOCS / "results"
PROVENANCE_KEYS = ("command", "git_revision", "machine", "date")
"""Keys every result file's ``provenance`` must hold, none of them empty."""

BLOCK = re.compile(
    r"(?P<open><!-- render: (?P<kind>[a-z0-9-]+)(?: (?P<file>[A-Za-z0-9_.\-/]+))? -->\n)"
    r"(?P<body>.*?)"
    r"(?P<close><!-- /render -->)",
    re.DOTALL,
)


# --- recording -----------------------------------------------------------------------------


def git_revision() -> str:
    """HEAD of this repository, with ``-dirty`` when tracked files other than the recorded
    results (docs/results/, docs/figures/: what recording writes) are modified."""
    if os.environ.get("AFBL_GIT_REVISION"):
        # a copy of the working tree on another machine (whose git folder, if any, need not be
        # the tree's): the revision it was copied from, as the caller states it
        return os.environ["AFBL_GIT_REVISION"]
    if not (ROOT / ".git").exists():
        return "unknown"
    sha = subprocess.run(
        ["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True, check=True
    ).stdout.strip()
    status = subprocess.run(
        ["git", "status", "--porcelain", "--untracked-files=no"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=True,
    ).stdout.splitlines()
    outputs = ("docs/results/", "docs/figures/")
    dirty = [line for line in status if not line[3:].startswith(outputs)]
    return sha + ("-dirty" if dirty else "")


def gpus() -> str:
    """The NVIDIA GPUs of this machine as ``nvidia-smi`` names them ("" when there is none)."""
    try:
        out = subprocess.run(
            ["nvidia-smi", "--query-gpu=name,memory.total", "--format=csv,noheader"],
            capture_output=True,
            text=True,
            timeout=30,
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return ""
    names = [line.strip() for line in out.splitlines() if line.strip()]
    return "; ".join(names)


def machine() -> str:
    """GPUs (if any), CPU model, core count, memory and operating system of this machine."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    memory = ""
    try:
        kb = int(Path("/proc/meminfo").read_text().split()[1])
        memory = f", {kb / 2**20:.0f} GiB memory"
    except (OSError, ValueError, IndexError):
        pass
    host = f"{cpu}, {os.cpu_count()} cores{memory}, {platform.platform()}"
    gpu = gpus()
    return f"GPU {gpu}; host {host}" if gpu else host


def load_average() -> str:
    try:
        return " ".join(Path("/proc/loadavg").read_text().split()[:3])
    except OSError:
        return "unknown"


def record(
    name: str, command: list[str], keep: list[str], copy: list[tuple[str, str]] = ()
) -> Path:
    """Run ``command`` in a temporary folder and write docs/results/NAME.json (see above);
    ``copy``: (file the command writes, destination relative to the repository) pairs, e.g. a
    figure for the documentation."""
    revision = git_revision()
    started = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
    load_start = load_average()
    with tempfile.TemporaryDirectory(prefix="afbl-record-") as work:
        # the repository's studies/ (distribution files, scripts) at the same relative path
        (Path(work) / "studies").symlink_to(ROOT / "studies")
        t0 = time.perf_counter()
        proc = subprocess.Popen(command, cwd=work, stdout=subprocess.PIPE, text=True)
        lines = []
        assert proc.stdout is not None
        for line in proc.stdout:
            sys.stdout.write(line)
            sys.stdout.flush()
            lines.append(line)
        rc = proc.wait()
        wall = time.perf_counter() - t0
        if rc != 0:
            raise SystemExit(f"record: {shlex.join(command)} exited with status {rc}")
        files = {path: json.loads((Path(work) / path).read_text()) for path in keep}
        for src, dest in copy:
            (ROOT / dest).write_bytes((Path(work) / src).read_bytes())
    doc = {
        "provenance": {
            "command": shlex.join(command),
            "git_revision": revision,
            "machine": machine(),
            "date": started,
            "load_average": f"{load_start} at the start, {load_average()} at the end",
            "wall_s": round(wall, 1),
        },
        "stdout": "".join(lines),
        "files": files,
    }
    RESULTS.mkdir(exist_ok=True)
    path = RESULTS / f"{name}.json"
    path.write_text(json.dumps(doc, indent=1) + "\n")
    return path


# --- rendering ------------------------------------------------------------------------------


def load(name: str) -> dict:
    """docs/results/NAME (a result file), checked for its provenance."""
    doc = json.loads((RESULTS / name).read_text())
    missing = [k for k in PROVENANCE_KEYS if not str(doc.get("provenance", {}).get(k, "")).strip()]
    if missing:
        raise ValueError(f"docs/results/{name}: provenance lacks {', '.join(missing)}")
    return doc


def provenance_line(doc: dict, load: bool = False) -> str:
    """One line naming the command, revision, machine and date behind a result file (and the
    load average the file records, with ``load``)."""
    p = doc["provenance"]
    line = (
        f"*Produced by `{p['command']}` at revision `{p['git_revision'][:12]}` on "
        f"{p['machine']}, {p['date'][:10]}"
    )
    if load and p.get("load_average"):
        line += f"; load average {p['load_average']}"
    return line + ".*"


def _fence(text: str) -> str:
    return "```\n" + text.rstrip("\n") + "\n```"


def _table(head: list[str], rows: list[list[str]], align: str | None = None) -> str:
    align = align or "l" + "r" * (len(head) - 1)
    rule = ["---:" if a == "r" else "---" for a in align]
    lines = ["| " + " | ".join(c.replace("|", "\\|") for c in head) + " |"]
    lines.append("| " + " | ".join(rule) + " |")
    lines += ["| " + " | ".join(c.replace("|", "\\|") for c in r) + " |" for r in rows]
    return "\n".join(lines)


def _files(doc: dict, suffix: str):
    """The one kept file of ``doc`` whose path ends with ``suffix``."""
    (path,) = [k for k in doc["files"] if k.endswith(suffix)]
    return doc["files"][path]


def render_reproduce(doc: dict) -> str:
    """The ISE table `afbl reproduce` prints, from the ise.json it wrote."""
    from afbl_jax.studies.reproduce import format_ise_json

    return _fence(format_ise_json(_files(doc, "ise.json"))) + "\n\n" + provenance_line(doc)


def render_reproduce_comparison(doc: dict) -> str:
    """The step scenarios' ISE (attitude / altitude) of each controller beside the paper's
    Tables 4/5, from the ise.json `afbl reproduce` wrote (|ISE| < 1e-9 shown as ~0)."""
    from afbl_jax.studies.reproduce import PAPER_ISE

    ise = _files(doc, "ise.json")

    def pair(vals) -> str:
        return " / ".join("~0" if abs(v) < 1e-9 else f"{v:.4g}" for v in vals)

    rows = []
    for kind in ("ideal", "uncertain"):
        per = ise[f"{kind}_step"]
        cells = [pair((per[c]["ise_attitude"], per[c]["ise_altitude"])) for c in per]
        paper = [pair(PAPER_ISE[kind][c]) for c in ("fbl", "afbl")]
        rows.append([f"{kind}, step", *cells, *paper])
    names = list(ise["ideal_step"])
    head = ["scenario", *[f"`{c}` att / alt" for c in names], "paper FBL", "paper AFBL"]
    return _table(head, rows, "l" * len(head)) + "\n\n" + provenance_line(doc)


def _bench_rows(doc: dict) -> list[dict]:
    return _files(doc, "bench.json")


GRADIENT_ROW = "tuning_gradient"
"""The benchmark rows of the tuning gradient (``afbl_jax.studies.bench_rows.GRADIENT_ROW``):
rendered by `render_bench_gradient`, not in the throughput tables."""


def render_bench_glance(doc: dict) -> str:
    """Simulations per second of each benchmark row against the scipy loop (compact)."""
    rows = [
        [
            f"`{r['strategy']}`",
            str(r["N"]),
            str(r["devices"]),
            r["dtype"],
            f"{r['sims_per_s']:.0f}",
            "-" if r.get("ratio_to_scipy") is None else f"{r['ratio_to_scipy']:.0f}x",
            "-" if r.get("max_rel_ise_error") is None else f"{r['max_rel_ise_error']:.1e}",
        ]
        for r in _bench_rows(doc)
        if r["strategy"] != GRADIENT_ROW  # its own table: bench-gradient
    ]
    head = ["row", "N", "devices", "dtype", "sims/s", "x scipy loop", "max rel. ISE error"]
    return _table(head, rows, "lrrlrrr") + "\n\n" + provenance_line(doc)


def render_bench_table(doc: dict) -> str:
    """Every column of a benchmark result file (bench.json rows)."""
    rows = []
    for r in _bench_rows(doc):
        steps = r.get("num_steps_max")
        rows.append(
            [
                f"`{r['strategy']}`",
                str(r["N"]),
                str(r["devices"]),
                r["dtype"],
                f"{r['rtol']:g} / {r['atol']:g}",
                f"{r['sims_per_s']:.1f}",
                "-" if r.get("ratio_to_scipy") is None else f"{r['ratio_to_scipy']:.1f}",
                f"{r['compile_s']:.1f}",
                "-" if steps is None else str(steps),
                "-" if r.get("max_rel_ise_error") is None else f"{r['max_rel_ise_error']:.2e}",
            ]
        )
    head = ["row", "N", "dev", "dtype", "rtol / atol", "sims/s", "x scipy", "compile s"]
    head += ["max steps", "max rel. ISE error"]
    return _table(head, rows, "lrrlrrrrrr") + "\n\n" + provenance_line(doc, load=True)


def render_bench_gradient(doc: dict) -> str:
    """The ``tuning_gradient`` rows of a benchmark result file: value-and-gradient against the
    forward pass of the same training cases."""
    rows = [
        [
            r["dtype"],
            f"{r['rtol']:g} / {r['atol']:g}",
            str(r["N"]),
            f"{r['forward_s']:.2f}",
            f"{r['gradient_s']:.2f}",
            f"{r['gradient_to_forward']:.1f}x",
            f"{r['gradient_to_forward_float32']:.1f}x",
            f"{r['compile_s']:.1f}",
            "-" if r["dtype"] == "float64" else f"{r['gradient_rel_error']:.1e}",
        ]
        for r in _bench_rows(doc)
        if r["strategy"] == GRADIENT_ROW
    ]
    head = ["dtype", "rtol / atol", "cases", "forward [s]", "value and gradient [s]"]
    head += ["/ its forward", "/ float32 forward", "gradient compile s"]
    head += ["float32 gradient error"]
    return _table(head, rows, "llrrrrrrr") + "\n\n" + provenance_line(doc, load=True)


def render_gradient_cost(doc: dict) -> str:
    """Forward and value-and-gradient times of `afbl tune-compare --study gradient-cost`."""
    d = _files(doc, "gradient_cost.json")
    rows = [
        [
            dtype,
            f"{d[dtype]['forward_s']:.2f}",
            f"{d[dtype]['gradient_s']:.2f}",
            f"{d[dtype]['gradient_s'] / d[dtype]['forward_s']:.1f}x",
        ]
        for dtype in ("float32", "float64")
    ]
    table = _table(["dtype", "forward [s]", "value and gradient [s]", "gradient / forward"], rows)
    extra = (
        f"\n\n{d['n_cases']} training cases. Float64 gradient / float32 forward: "
        f"{d['ratio_gradient64_to_forward32']:.1f}x; float32 gradient against the float64 one: "
        f"{d['float32_gradient_rel_error']:.1e} of its largest entry."
    )
    return table + extra + "\n\n" + provenance_line(doc)


def render_tuning_optimizers(doc: dict) -> str:
    """Final training objective per seed and optimiser (`--study optimizers`)."""
    d = _files(doc, "optimizers.json")
    final, runs = d["final"], d["runs"]
    methods = list(final)
    seeds = list(final[methods[0]])
    rows = []
    for seed in seeds:
        start = runs[methods[0]][seed][0]
        best = min(final[m][seed] for m in methods)
        cells = []
        for m in methods:
            v = final[m][seed]
            steps = runs[m][seed][1:]
            if m == "hybrid":  # CMA-ES generations (no gradient norm), then L-BFGS iterations
                gens = sum(1 for h in steps if h["grad_norm"] != h["grad_norm"])
                count = f"{gens} gen. + {len(steps) - gens} it."
            else:
                count = f"{len(steps)} {'gen.' if m == 'cmaes' else 'it.'}"
            text = f"{v:.3f} ({count})"
            cells.append(f"**{text}**" if v == best else text)
        rows.append([f"{seed} ({start['failed']} failed)", f"{start['loss']:.3f}", *cells])
    head = ["seed (cases failed at the start)", "start", *methods]
    return _table(head, rows, "lr" + "r" * len(methods)) + "\n\n" + provenance_line(doc)


def render_tuning_controllers(doc: dict) -> str:
    """The held-out table `afbl tune-compare --study controllers` writes (controllers.txt)."""
    from afbl_jax.studies.tuning import format_controllers

    table = format_controllers(_files(doc, "controllers.json")["heldout"])
    return _fence(table) + "\n\n" + provenance_line(doc)


def render_tune_run(doc: dict) -> str:
    """One recorded `afbl tune`: the training size, the iterations its time budget held, the
    training objective, and the held-out statistics of the paper's and the tuned gains
    (evaluation.json), with the command's wall time."""
    e = _files(doc, "evaluation.json")
    cfg = e["meta"]["config"]
    iterations = sum(1 for line in doc["stdout"].splitlines() if re.match(r"iteration \d+/", line))
    wall = doc["provenance"].get("wall_s")
    budget = cfg.get("time_budget")
    run = [
        [
            str(cfg["n_cases"]),
            cfg["objective"]["dtype"],
            "-" if budget is None else f"{budget:g}",
            str(iterations),
            f"{e['initial_loss']:.4f} -> {e['final_loss']:.4f}",
            "-" if wall is None else f"{wall:.0f}",
        ]
    ]
    head = ["training cases", "dtype", "budget s", "iterations", "objective", "command wall s"]
    rows = []
    for gains in ("paper", "tuned"):
        h = e["heldout"][gains]
        lo, hi = h["failure_wilson95"]
        rows.append(
            [
                gains,
                f"{h['ise']['p50']:.3e}",
                f"{h['ise']['cvar90']:.3e}",
                f"{h['effort']['p50']:.2f}",
                f"{h['failures']} / {h['n_cases']} ({100 * lo:.2f}-{100 * hi:.2f} %)",
            ]
        )
    held = ["gains", "ISE P50", "ISE CVaR0.9", "effort P50", "failures (95 % Wilson)"]
    n_out = e["heldout"]["paper"]["outside_envelope"]
    return (
        _table(head, run, "rlrrrr")
        + "\n\n"
        + f"Held-out cases inside the flight envelope ({n_out} outside it left out), sensor "
        + "noise on; ISE = ISE_att + ISE_alt [rad² s + m² s]:\n\n"
        + _table(held, rows, "lrrrr")
        + "\n\n"
        + provenance_line(doc, load=True)
    )


def render_unmodeled(doc: dict) -> str:
    """The grid tables `afbl unmodeled` prints (its standard output after the progress lines)."""
    text = doc["stdout"]
    start = re.search(r"^\w+: paper model", text, re.MULTILINE)
    if start is None:
        raise ValueError("the recorded output holds no grid table")
    end = text.find("\nwrote ", start.start())
    return _fence(text[start.start() : None if end < 0 else end]) + "\n\n" + provenance_line(doc)


def render_montecarlo_summary(doc: dict) -> str:
    """The summary tables `afbl montecarlo` prints, from the summary.json it wrote (Markdown)."""
    from afbl_jax.studies.montecarlo import summary_tables

    parts = []
    for title, header, rows in summary_tables(_files(doc, "summary.json")):
        parts += [f"**{title}**", "", _table(header, rows, "l" + "r" * (len(header) - 1)), ""]
    return "\n".join(parts) + "\n" + provenance_line(doc)


def render_montecarlo_glance(doc: dict) -> str:
    """The flight-envelope, failure and paired-win tables of a recorded `afbl montecarlo`
    run (the README's short form of `render_montecarlo_summary`)."""
    from afbl_jax.studies.montecarlo import summary_tables

    keep = ("flight envelope", "failures of flyable cases", "paired win rate")
    parts = []
    for title, header, rows in summary_tables(_files(doc, "summary.json")):
        if title.startswith(keep):
            parts += [f"**{title}**", "", _table(header, rows, "l" + "r" * (len(header) - 1)), ""]
    return "\n".join(parts) + "\n" + provenance_line(doc)


def render_rare_event(doc: dict) -> str:
    """P(failure) of each controller from the rare_event.json `afbl montecarlo --estimator`
    wrote."""
    d = _files(doc, "rare_event.json")["rare_event"]
    rows = [
        [
            f"`{name}`",
            f"{e['probability']:.2e}",
            f"[{e['ci95'][0]:.2e}, {e['ci95'][1]:.2e}]",
            f"{e['cv']:.2f}",
            str(e["total_simulations"]),
            f"{e['seconds']:.0f}",
        ]
        for name, e in d["controllers"].items()
    ]
    head = ["controller", "P(failure)", "95 % interval", "cv", "simulations", "time [s]"]
    return (
        f"Estimator: {d['estimator']}.\n\n"
        + _table(head, rows, "lrrrrr")
        + "\n\n"
        + provenance_line(doc)
    )


def render_study_time(doc: dict) -> str:
    """The seconds of each phase of a recorded `afbl montecarlo` (``phases_seconds`` of the
    meta.json it wrote) and the command's wall time."""
    meta = _files(doc, "meta.json")
    phases = meta["phases_seconds"]
    names = ["startup", "compilation", "runs", "report", "total"]
    cells = ["-" if phases.get(n) is None else f"{phases[n]:.1f}" for n in names]
    head = ["start-up and imports s", "tracing and compilation s", "runs s", "report s"]
    head += ["total s", "command wall s"]
    wall = doc["provenance"].get("wall_s")
    rows = [[*cells, "-" if wall is None else f"{wall:.1f}"]]
    return _table(head, rows, "r" * len(head)) + "\n\n" + provenance_line(doc, load=True)


def render_command_time(doc: dict) -> str:
    """The wall time of a recorded command (``provenance.wall_s``), e.g. ``afbl --help``."""
    wall = doc["provenance"].get("wall_s")
    rows = [[f"`{doc['provenance']['command']}`", "-" if wall is None else f"{wall:.1f}"]]
    return _table(["command", "wall s"], rows, "lr") + "\n\n" + provenance_line(doc, load=True)


def render_turbulence_band(doc: dict) -> str:
    """`studies/turbulence_band.py`: lines, run time and solver steps of the default study with
    the lines up to the cutoff and with every line; the variance the cutoff keeps; the
    relative change of each case's ISE."""
    band = _files(doc, "turbulence_band.json")
    rows = [
        [
            "up to `omega_cutoff`" if key == "cutoff" else "every line of the grid",
            str(v["lines"]),
            f"{v['top_line_rad_s']:.1f}",
            f"{v['runs_s']:.1f}",
            ", ".join(f"{c} {s:.0f}" for c, s in v["median_solver_steps"].items()),
        ]
        for key, v in band["variants"].items()
    ]
    head = ["turbulence lines", "lines", "top line rad/s", "runs s", "median solver steps"]
    out = [_table(head, rows, "lrrrl")]
    rows = [
        [ax, f"{100 * v['total']:.2f} %", f"{100 * v['least']:.2f} %"]
        for ax, v in band["variance_kept"].items()
    ]
    out.append(_table(["axis", "variance kept, all cases", "least kept, one case"], rows))
    rows = []
    for c, e in band["ise_relative_difference"].items():
        for metric in ("ise_attitude", "ise_altitude", "ise_position"):
            d = e[metric]
            rows.append(
                [
                    c,
                    metric,
                    f"{d['median']:.1e}",
                    f"{d['p99']:.1e}",
                    f"{d['max']:.1e}",
                    f"{d['above_1e-3']}/{e['runs_ok_in_both']}",
                    str(e["status_changed"]),
                ]
            )
    head = ["controller", "metric", "median", "P99", "max", "cases > 1e-3", "status changed"]
    out.append(_table(head, rows, "llrrrrr"))
    return "\n\n".join(out) + "\n\n" + provenance_line(doc, load=True)


def render_test_times(doc: dict) -> str:
    """Seconds per test file of the default test run (`studies/test_times.py`), with the JAX
    work of its test processes (tracing and lowering seconds, XLA programs compiled, those of
    1 s or more, XLA seconds) and the run's CPU time."""
    t = _files(doc, "test_times.json")
    files = t["files"]
    columns = {  # header -> the row's key, summed over the rows of a line
        "tests": "tests",
        "seconds": "seconds",
        "trace + lower s": "trace_lower_s",
        "programs compiled": "compiled",
        "of them >= 1 s": "compiled_1s",
        "XLA s": "xla_s",
    }

    def cells(name, rows):
        return [name] + [f"{sum(r[key] for r in rows):.0f}" for key in columns.values()]

    table = [cells(f"`{r['file']}`", [r]) for r in files]
    table.append(cells("all files (worker time)", files))
    summary = (
        f"Wall time {t['wall_s']:.0f} s ({t['wall_s'] / 60:.1f} min): {t['passed']} passed, "
        f"{t['failed']} failed, {t['skipped']} skipped. CPU time of all its processes "
        f"{t['cpu_s']:.0f} s, {t['cpu_s'] / t['wall_s']:.2f} cores busy on average."
    )
    return (
        _table(["test file", *columns], table)
        + "\n\n"
        + summary
        + "\n\n"
        + provenance_line(doc, load=True)
    )


RENDERERS: dict[str, Callable[[dict], str]] = {
    "montecarlo-summary": render_montecarlo_summary,
    "montecarlo-glance": render_montecarlo_glance,
    "rare-event": render_rare_event,
    "reproduce-table": render_reproduce,
    "reproduce-comparison": render_reproduce_comparison,
    "bench-glance": render_bench_glance,
    "bench-table": render_bench_table,
    "bench-gradient": render_bench_gradient,
    "gradient-cost": render_gradient_cost,
    "tuning-optimizers": render_tuning_optimizers,
    "tuning-controllers": render_tuning_controllers,
    "tune-run": render_tune_run,
    "unmodeled-grid": render_unmodeled,
    "test-times": render_test_times,
    "study-time": render_study_time,
    "command-time": render_command_time,
    "turbulence-band": render_turbulence_band,
}
"""Kind -> function of a result file's document (with its provenance) to Markdown."""


def distribution_reference() -> str:
    """Every section and key of `DEFAULT_DISTRIBUTION` with its default and the comment written
    beside it in afbl_jax/studies/montecarlo/_distribution.py."""
    import ast
    import io
    import tokenize

    from afbl_jax.studies.montecarlo import DEFAULT_DISTRIBUTION
    from afbl_jax.studies.montecarlo import _distribution as module

    source = Path(module.__file__).read_text()
    comments = {
        tok.start[0]: tok.string.lstrip("#").strip()
        for tok in tokenize.generate_tokens(io.StringIO(source).readline)
        if tok.type == tokenize.COMMENT
    }
    lines = source.splitlines()
    (node,) = [
        n.value
        for n in ast.parse(source).body
        if isinstance(n, ast.AnnAssign) and getattr(n.target, "id", "") == "DEFAULT_DISTRIBUTION"
    ]

    def note(key_node, previous_end: int) -> str:
        # comment lines standing alone above the key, then the comment on its own line
        above = [
            comments[i]
            for i in range(previous_end + 1, key_node.lineno)
            if i in comments and lines[i - 1].strip().startswith("#")
        ]
        return " ".join(
            above + ([comments[key_node.lineno]] if key_node.lineno in comments else [])
        )

    out = []
    for sec_key, sec_val in zip(node.keys, node.values, strict=True):
        section = sec_key.value
        out.append(f"### `[{section}]`\n")
        if sec_key.lineno in comments and sec_val.lineno == sec_key.lineno:
            if isinstance(sec_val, ast.Dict) and sec_val.end_lineno != sec_key.lineno:
                out.append(comments[sec_key.lineno] + "\n")
        rows = []
        previous = sec_key.lineno
        for key_node, _ in zip(sec_val.keys, sec_val.values, strict=True):
            value = DEFAULT_DISTRIBUTION[section][key_node.value]
            text = note(key_node, previous) if key_node.lineno != sec_key.lineno else ""
            rows.append([f"`{key_node.value}`", f"`{json.dumps(value)}`", text])
            previous = key_node.lineno
        out.append(_table(["key", "default", "meaning"], rows, "lll") + "\n")
    return "\n".join(out).rstrip("\n")


GENERATED: dict[str, Callable[[], str]] = {"distribution-reference": distribution_reference}
"""Kind -> function generating Markdown from the code (no result file)."""


def render_block(kind: str, file: str | None) -> str:
    if kind in GENERATED:
        if file:
            raise ValueError(f"render kind {kind!r} takes no file, got {file!r}")
        return GENERATED[kind]()
    if kind not in RENDERERS:
        raise ValueError(f"unknown render kind {kind!r}; known: {', '.join(RENDERERS)}")
    if not file:
        raise ValueError(f"render kind {kind!r} needs a result file")
    return RENDERERS[kind](load(file))


def render_text(text: str) -> str:
    """``text`` with every rendered block replaced by its current rendering."""

    def replace(m: re.Match) -> str:
        body = render_block(m["kind"], m["file"])
        return f"{m['open']}{body}\n{m['close']}"

    return BLOCK.sub(replace, text)


def markdown_files() -> list[Path]:
    """README.md and every Markdown page of the documentation."""
    return [ROOT / "README.md", *sorted(DOCS.rglob("*.md"))]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python docs/results.py", description=__doc__.split("\n")[0]
    )
    sub = parser.add_subparsers(dest="action", required=True)
    rec = sub.add_parser("record", help="run a command and keep its output with provenance")
    rec.add_argument("name", help="result file docs/results/NAME.json")
    rec.add_argument("--keep", action="append", default=[], help="JSON file the command writes")
    rec.add_argument(
        "--copy",
        nargs=2,
        action="append",
        default=[],
        metavar=("FILE", "DEST"),
        help="copy a file the command writes to DEST (relative to the repository)",
    )
    argv = sys.argv[1:] if argv is None else argv
    command = argv[argv.index("--") + 1 :] if "--" in argv else []
    ren = sub.add_parser("render", help="rewrite the rendered blocks of README.md and docs/")
    ren.add_argument("--check", action="store_true", help="only report blocks that differ")
    args = parser.parse_args(argv[: argv.index("--")] if "--" in argv else argv)
    if args.action == "render":
        stale = []
        for path in markdown_files():
            text = path.read_text()
            new = render_text(text)
            if new != text:
                stale.append(path.relative_to(ROOT))
                if not args.check:
                    path.write_text(new)
        verb = "differ from their result files" if args.check else "rewritten"
        print(f"{len(stale)} file(s) {verb}: {', '.join(map(str, stale)) or '-'}")
        return 1 if stale and args.check else 0
    if args.action == "record":
        if not command:
            parser.error("record: no command given (python docs/results.py record NAME -- CMD)")
        print(f"wrote {record(args.name, command, args.keep, args.copy)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
