"""Planning a sweep's work: which runs are pending, which finished results a pending run
can take over (`reuse_finished`), the jobs (`make_jobs`: one per row, its seeds as
members) and how jobs are packed into worker processes so that rows sharing a compiled
program meet in one (`job_programs`, `pack_jobs`). Nothing here trains or evaluates:
`experiments.runner` executes the jobs. Also the JSON files of a results directory
(`_write_json`, `_read_json`).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from experiments import studies as st


def _write_json(path: Path, data: Any) -> None:
    """Writes JSON atomically (a reader never sees half a metrics.json)."""
    from dmd_jax.io import write_text_atomic

    path.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(path, json.dumps(data, indent=2, allow_nan=True) + "\n")


def _read_json(path: Path) -> Any:
    return json.loads(Path(path).read_text())


def _spec_to_json(r: st.RunSpec) -> dict:
    return {
        "study": r.study,
        "row": r.row,
        "seed": r.seed,
        "config": r.config.to_dict(),
        "evaluation": r.evaluation,
        "train_hash": r.train_hash,
        "run_id": r.run_id,
    }


def seedless_hash(cfg) -> str:
    """The training hash with `train.seed` left out: the seeds of one row share it."""
    return st.config_hash(cfg.with_edits({"train": {"seed": 0}}))


def _evaluation_key(train_hash: str, evaluation: dict) -> str:
    return train_hash + json.dumps(evaluation, sort_keys=True)


def reuse_finished(
    runs: Sequence[st.RunSpec], sources: Sequence[st.RunSpec], out_dir: Path, log
) -> list[str]:
    """Writes the `metrics.json` of every run in `runs` that has none but whose model and
    evaluation (training hash, evaluation spec) some finished run of `sources` already
    has: its metrics are those, not a retraining's.

    Within one checkout the runner reuses the trained model (its checkpoints); this
    reuses the *result*, which is what a fresh checkout has, since checkpoints are not
    committed. Without it a study whose base row another study already scored retrains
    it, and the retrained seeds differ from the committed ones (XLA's CPU reductions are
    not bitwise reproducible across processes), so one row would have two values.

    Returns the `study/run_id` of the runs written.
    """
    finished: dict[str, tuple[st.RunSpec, dict]] = {}
    for r in sources:
        path = out_dir / r.study / r.run_id / "metrics.json"
        if path.is_file():
            finished.setdefault(_evaluation_key(r.train_hash, r.evaluation), (r, _read_json(path)))
    written = []
    for r in runs:
        run_dir = out_dir / r.study / r.run_id
        if (run_dir / "metrics.json").is_file():
            continue
        hit = finished.get(_evaluation_key(r.train_hash, r.evaluation))
        if hit is None:
            continue
        src, record = hit
        src_rel, rel = f"{src.study}/{src.run_id}", f"{r.study}/{r.run_id}"
        record = {
            **record,
            "study": r.study,
            "row": r.row,
            "seed": r.seed,
            "run_id": r.run_id,
            "results_of": src_rel,
        }
        run_dir.mkdir(parents=True, exist_ok=True)
        _write_json(run_dir / "config.json", r.config.to_dict())
        (run_dir / "run.log").write_text(
            f"run {rel}: study {r.study}, row {r.row!r}, seed {r.seed}\n"
            f"config hash {r.train_hash}, evaluation {r.evaluation['kind']}: the same "
            f"model and evaluation as {src_rel}, whose metrics.json this copies "
            f"(trained in {record.get('trained_in', src_rel)})\n"
        )
        _write_json(run_dir / "metrics.json", record)
        written.append(rel)
    if written:
        log(f"{len(written)} runs reuse the results of finished runs (same model, evaluation)")
    return written


def make_jobs(
    runs: Sequence[st.RunSpec],
    out_dir: Path,
    *,
    data_dir,
    preset_name,
    eval_meshes,
    progress,
    seeds_together: int | None = None,
) -> list[dict]:
    """One job per row (configs equal up to the seed) that still has a run without
    `metrics.json`; its members are the row's seeds (one training hash each)."""
    homes = st.training_homes(runs)
    pending: dict[str, dict[str, list[st.RunSpec]]] = {}
    for r in runs:
        if not (out_dir / r.study / r.run_id / "metrics.json").is_file():
            row = pending.setdefault(seedless_hash(r.config), {})
            row.setdefault(r.train_hash, []).append(r)
    jobs = []
    for by_hash in pending.values():
        members = []
        for h, rs in by_hash.items():
            home = homes[h]
            members.append(
                {
                    "home": f"{home.study}/{home.run_id}",
                    "config": home.config.to_dict(),
                    "runs": [_spec_to_json(r) for r in rs],
                    "trained": (
                        out_dir / home.study / home.run_id / "train_metrics.json"
                    ).is_file(),
                }
            )
        first = homes[next(iter(by_hash))]
        steps = first.config.train.steps
        jobs.append(
            {
                "out_dir": str(out_dir),
                "data_dir": str(data_dir),
                "eval_meshes": eval_meshes,
                "seeds_together": seeds_together,
                "preset": preset_name,
                "label": f"{first.study}/{st.slug(first.row)}",
                "members": members,
                "progress": progress,
                # What the remaining-time estimate weighs a job by: its training steps
                # (a row's seeds cost about one seed's steps, see seed_speedup.md) plus
                # a tenth for its evaluations.
                "cost": (steps if any(not m["trained"] for m in members) else 0) + 0.1 * steps,
            }
        )
    return jobs


# What compiling one program costs, in the unit of a job's `cost` (training steps), when
# rows are packed into worker processes: a test-preset train step compiles in ~20 s of
# CPU and runs in ~35 ms, a cpu-preset step in ~0.2 s; 100 steps is between the two.
COMPILE_COST_STEPS = 100


def job_programs(job: dict) -> list[str]:
    """Short ids of the programs a job compiles: `step:<digest>`, the one train-step
    program of every phase of its row (`train.step_program_key`; none when every seed
    is trained already) and `model:<digest>`, its model's init and predictor (dropout
    left out: both run the model deterministic)."""
    from dmd_jax.config import ExperimentConfig
    from dmd_jax.train import step_program_key

    cfg = ExperimentConfig.from_dict(job["members"][0]["config"])
    out = {"model:" + st._digest(cfg.model.with_edits({"dropout": 0.0}).to_dict())}
    if any(not m["trained"] for m in job["members"]):
        out.add("step:" + st._digest(step_program_key(cfg)))
    return sorted(out)


def pack_jobs(jobs: Sequence[dict], workers: int) -> list[list[dict]]:
    """The jobs in tasks for `workers` processes, rows that share programs in one task.

    A task runs in one process, one job after the other, so a later row reuses what an
    earlier one compiled (`multiseed.seeds_step`'s shared programs, the model's init
    and predictor) instead of compiling it in the other process as well. Rows that
    share a train-step program always go together; rows that share only a model join
    while the task stays within an even share of the sweep's cost (training steps plus
    `COMPILE_COST_STEPS` per distinct program), so that no task outgrows one process's
    share. Tasks come largest first, for the pool to balance; jobs keep plan order.

    Args:
      jobs: `make_jobs` jobs with `programs` (`job_programs`).
      workers: processes.

    Returns:
      Lists of jobs, together all of `jobs`.
    """
    n = len(jobs)
    parent = list(range(n))

    def find(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    def groups():
        out: dict[int, list[int]] = {}
        for i in range(n):
            out.setdefault(find(i), []).append(i)
        return out

    def cost(members):
        programs = {p for i in members for p in jobs[i]["programs"]}
        return sum(jobs[i]["cost"] for i in members) + COMPILE_COST_STEPS * len(programs)

    first: dict[str, int] = {}
    for i, job in enumerate(jobs):
        for prog in job["programs"]:
            if prog.startswith("step:"):
                if prog in first:
                    parent[find(i)] = find(first[prog])
                else:
                    first[prog] = i
    cap = cost(range(n)) / max(int(workers), 1)
    by_model: dict[str, list[int]] = {}
    for i, job in enumerate(jobs):
        for prog in job["programs"]:
            if prog.startswith("model:"):
                by_model.setdefault(prog, []).append(i)
    for members in by_model.values():
        for i in members[1:]:
            a, b = find(members[0]), find(i)
            if a != b:
                g = groups()
                if cost(g[a] + g[b]) <= cap:
                    parent[b] = a
    tasks = sorted(groups().values(), key=lambda m: -cost(m))
    return [[jobs[i] for i in sorted(m)] for m in tasks]
