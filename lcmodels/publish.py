"""Copy an ``lc-experiment`` directory's report and small result files to a folder meant for git.

:func:`publish` copies ``REPORT.md``, the figures, ``experiment.json``, ``invocations.json``, the complete
stage records (``stages/*.json``) and, per stage, ``metrics.json`` / ``run.json`` / ``progress.csv`` /
``warm_start.json`` / ``dagger.json`` / a suite stage's ``suite.json`` and finished roads / the bench stage's table and figures: every figure the report shows, and nothing large (no checkpoints,
TensorBoard logs or MCAP episodes). It refuses a run without a report or with unfinished stages, and a
destination that exists unless ``overwrite``; then it replaces only files of that layout (and removes
those of it the run no longer has), keeping anything else there (a note written by hand).

With ``weights`` it also copies each stage's final ``policy.safetensors`` and the ``predictor.pt`` (a few
hundred KB each): the folder is then an experiment directory that resumes. Copied to a working place and run
again with the same command, it re-records the corpus and the demonstrations (the same bytes: their stage
records still match), skips every finished stage, and goes on with what is new (another seed, another
recipe): a long run spans machines and checkouts through git.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

from lckit.fileio import (
    check_inside,
    check_target,
    file_sha256,
    read_json,
    remove_file,
    write_file,
    write_json,
)
from lcmodels.presets import INVOCATIONS, MARKER, ORACLE_KEY, REPORT_NAME, RULE_KEY, STAGES_DIR

TOP = (REPORT_NAME, MARKER)
OPTIONAL_TOP = (INVOCATIONS,)  # runs of lc-toolkit versions before it have none
PER_STAGE = ("metrics.json", "run.json", "progress.csv", "warm_start.json", "dagger.json", "suite.json", "BENCH.md",
             "bench.json")
WEIGHTS = ("policy.safetensors", "predictor.pt")
"""A stage's final weights (not its checkpoints): what a later stage reads from a finished one."""
SPLIT_FILES = "*-seed*.json"
"""An evaluation stage's finished splits (``val-seed0.json``, ``test-seed9.json``): an interrupted one's too."""
SUITE_CELLS = "cells/*.json"
"""A suite stage's finished roads (lc-bench's cells): an interrupted one's too."""


def published_files(run: Path, *, weights: bool = False) -> list[Path]:
    """Paths (relative to ``run``) of the files to publish (``weights``: the stages' final weights too)."""
    files = [Path(n) for n in TOP if n != REPORT_NAME or (run / n).is_file()]  # a stopped run may have no report yet
    files += [Path(n) for n in OPTIONAL_TOP if (run / n).is_file()]
    files += sorted(p.relative_to(run) for p in run.glob("*.png"))
    files += sorted(p.relative_to(run) for p in (run / STAGES_DIR).glob("*.json") if not p.name.endswith(".pending.json"))
    stage_dirs = [run / "predictor", *sorted(p for p in (run / "analytic-predictor").glob("*") if p.is_dir()), run / RULE_KEY,
                  run / ORACLE_KEY, *sorted(run.glob("policies/*/seed*/*")),
                  *sorted(run.glob("policies/*/seed*/dagger/round*")), *sorted(run.glob("zoo/*")),
                  *sorted(p for p in run.glob("suite/*") if p.is_dir()), run / "bench"]
    per_stage = PER_STAGE + WEIGHTS if weights else PER_STAGE
    for d in stage_dirs:
        files += [(d / n).relative_to(run) for n in per_stage if (d / n).is_file()]
        files += sorted(p.relative_to(run) for p in d.glob(SPLIT_FILES))  # an evaluation's finished splits
        files += sorted(p.relative_to(run) for p in d.glob(SUITE_CELLS))  # a suite stage's finished roads
        files += sorted(p.relative_to(run) for p in d.glob("bench_*.*") if d.name == "bench")  # its figures
    return files


TEXT_SUFFIXES = (".json", ".csv", ".md")
"""Published files that may name the run's own folder as the machine spelt it (a config's demonstrations or
previous policy): published with those paths relative to the run. The weights are copied as they are."""


def _relative(run: Path, rel: Path) -> bytes:
    """The bytes of ``run/rel`` to publish: a text file with the run's own absolute path (as JSON writes it) made
    relative to the run, so that no committed file names the machine's folders."""
    data = (run / rel).read_bytes()
    if rel.suffix not in TEXT_SUFFIXES:
        return data
    prefix = json.dumps(str(Path(run).resolve()) + "/")[1:-1].encode()
    return data.replace(prefix, b"")


def _rehash_records(dest: Path) -> None:
    """The complete stage records of ``dest`` made true of the files published beside them: an output whose bytes
    :func:`_relative` changed gets its new SHA-256, and every stage that read it the new digest among its inputs
    (a stage's digest is its outputs' alone: one pass). The run then resumes from ``dest`` as it would have."""
    from lcmodels.experiment.keys import StageKey
    from lcmodels.presets import outputs_digest

    records = {p: read_json(p) for p in sorted((dest / STAGES_DIR).glob("*.json")) if not p.name.endswith(
        ".pending.json")}  # fmt: skip
    renamed: dict[str, str] = {}
    for record in records.values():
        if not isinstance(record, dict) or not isinstance(record.get("outputs"), dict):
            continue
        folder = StageKey.parse(str(record.get("stage"))).path(dest)
        outputs = {name: (file_sha256(folder / name) if (folder / name).is_file() else sha)
                   for name, sha in record["outputs"].items()}  # fmt: skip
        if outputs != record["outputs"]:
            renamed[outputs_digest(record["outputs"])] = outputs_digest(outputs)
            record["outputs"] = outputs
    for path, record in records.items():
        if isinstance(record, dict) and isinstance(record.get("inputs"), dict):
            record["inputs"] = {role: renamed.get(d, d) for role, d in record["inputs"].items()}
            write_json(path, record)


def publish(run: Path, dest: Path, *, overwrite: bool = False, allow_pending: bool = False,
            weights: bool = False) -> list[Path]:
    """Copy the published files of ``run`` to ``dest``; returns their paths relative to both.

    ``allow_pending``: publish a run with unfinished stages (their pending records stay behind; what they
    finished, such as an evaluation's completed splits, is copied), for a run stopped on purpose.
    ``weights``: copy the stages' final weights too, so that ``dest`` resumes as an experiment directory.

    Raises:
        ValueError: ``run`` is no finished experiment (unless ``allow_pending``), or ``dest`` exists and not
            ``overwrite``.
    """
    run, dest = Path(run), Path(dest)
    if not (run / MARKER).is_file() or not ((run / REPORT_NAME).is_file() or allow_pending):
        raise ValueError(f"{run} is not an lc-experiment directory with a {REPORT_NAME}")
    pending = sorted(p.name for p in (run / STAGES_DIR).glob("*.pending.json"))
    if pending and not allow_pending:
        raise ValueError(f"{run} has {len(pending)} unfinished stage(s) ({pending[0]}); finish the run first, "
                         "or publish it as it is with --allow-pending")
    if dest.exists() and not overwrite:
        raise ValueError(f"{dest} exists; pass --overwrite to replace the published files in it")
    files = published_files(run, weights=weights)
    for rel in files:  # never read out of the run, never written through a link out of ``dest``
        check_inside(run / rel, run)
        check_target(dest / rel, dest)
    if dest.exists():  # the layout's files the run no longer has go; nothing else is touched
        stale = set(published_files(dest, weights=weights)) - set(files)
        for rel in stale:
            remove_file(dest / rel, dest)
    for rel in files:
        write_file(dest / rel, _relative(run, rel), root=dest)
        shutil.copystat(run / rel, dest / rel)
    _rehash_records(dest)
    return files
