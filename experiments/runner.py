"""Runs a sweep: dataset, curvature calibration, training jobs, evaluations, results.

Layout of a results directory (default `experiments/results/<preset>`)::

    plan.json                      every run of every study at this preset
    ablate.log                     one line per event, with timestamps
    sessions.json                  wall and CPU time of every invocation
    <study>/<run-id>/config.json   the run's ExperimentConfig
    <study>/<run-id>/metrics.json  its results (present = finished; reruns skip it)
    <study>/<run-id>/run.log       where it was trained, how long it took, on what
    <study>/<run-id>/log.jsonl     per-step training log (in the run that trained)
    <study>/<run-id>/checkpoints/  Orbax checkpoints (gitignored; train() resumes here)

Runs with the same training hash (equal configs up to the name) train once, in the
directory of the first of them in plan order, and the others reuse that model. A job is
one training hash: train it (or resume, or find it finished), then evaluate every pending
run that uses it. Jobs run in `workers` spawned processes.

This module executes; what to run is planned in `experiments.studies` (the runs) and
`experiments.planning` (the jobs and their packing into processes), and what a run is
scored on lives in `experiments.evaluation`. The per-run files stay out of git
(`.gitignore`): a results directory in the repository holds the summaries and plan.json.
"""

from __future__ import annotations

import concurrent.futures
import functools
import math
import multiprocessing
import os
import platform
import resource
import shutil
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from experiments import studies as st
from experiments.evaluation import (
    EVAL_SEED,
    ensure_references,
    evaluate_checkpoint,
    noise_evaluation,
    rotation_evaluation,
)
from experiments.planning import (
    _read_json,
    _spec_to_json,
    _write_json,
    job_programs,
    make_jobs,
    pack_jobs,
    reuse_finished,
)

CALIBRATION_FILE = "ablate-calibration.json"
CALIBRATION_MESHES = 64


# --------------------------------------------------------------------------------------
# Environment
# --------------------------------------------------------------------------------------


def apply_xla_opt_level(level: int | None) -> str:
    """Adds `--xla_backend_optimization_level=level` to `XLA_FLAGS` (unless set already).

    XLA reads the flag when the backend starts, so this must run before the first JAX
    computation of the process; spawned workers inherit it.
    """
    flags = os.environ.get("XLA_FLAGS", "")
    if level is not None and "xla_backend_optimization_level" not in flags:
        flags = f"{flags} --xla_backend_optimization_level={int(level)}".strip()
        os.environ["XLA_FLAGS"] = flags
    return flags


def enable_compilation_cache(path=None) -> Path:
    """Turns on JAX's persistent compilation cache in this process and its workers."""
    import jax

    path = Path(
        path
        or os.environ.get("ABLATE_JAX_CACHE")
        or Path.home() / ".cache" / "dmd_jax" / "xla-ablate"
    )
    path.mkdir(parents=True, exist_ok=True)
    os.environ["JAX_COMPILATION_CACHE_DIR"] = str(path)  # spawned workers read this
    jax.config.update("jax_compilation_cache_dir", str(path))
    return path


def host_info() -> dict[str, Any]:
    """What the numbers were measured on."""
    import jax

    cpu_model = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu_model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {
        "platform": platform.platform(),
        "processor": cpu_model,
        "cpu_count": os.cpu_count(),
        "python": platform.python_version(),
        "jax": jax.__version__,
        "backend": jax.default_backend(),
        "devices": [str(d) for d in jax.devices()],
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
    }


# --------------------------------------------------------------------------------------
# Data
# --------------------------------------------------------------------------------------


def _expected_generator(p: st.AblatePreset) -> dict[str, Any]:
    from dmd_jax.data import CATEGORIES

    return {
        "categories": list(CATEGORIES if p.categories is None else p.categories),
        "per_category": p.per_category,
        "min_vertices": p.min_vertices,
        "max_vertices": p.max_vertices,
    }


def ensure_dataset(p: st.AblatePreset, data_dir, *, progress: bool = True):
    """The preset's dataset in `data_dir`, generated once (seeds fixed) and reused.

    Raises:
      ValueError: `data_dir` holds a dataset made with other settings.
    """
    from dmd_jax.data import load_dataset, make_dataset

    data_dir = Path(data_dir)
    if (data_dir / "manifest.json").is_file():
        ds = load_dataset(data_dir)
        m = ds.manifest
        got = {k: m.get("generator", {}).get(k) for k in _expected_generator(p)}
        want = _expected_generator(p)
        same = (
            got == want
            and m.get("seed") == p.data_seed
            and list(m.get("test_inter", [])) == list(p.test_inter)
            and m.get("intra_fraction") == p.intra_fraction
        )
        if not same:
            raise ValueError(
                f"{data_dir} holds a dataset made with other settings ({got}, seed "
                f"{m.get('seed')}); remove it or pass another --data-dir"
            )
        return ds
    return make_dataset(
        data_dir,
        per_category=p.per_category,
        seed=p.data_seed,
        categories=p.categories,
        test_inter=p.test_inter,
        intra_fraction=p.intra_fraction,
        workers=p.dataset_workers,
        min_vertices=p.min_vertices,
        max_vertices=p.max_vertices,
        progress=progress,
    )


@functools.lru_cache(maxsize=4)
def load_examples(data_dir: str, eval_meshes: int | None):
    """`(train examples, {"test_intra": [...], "test_inter": [...]})`, graphs built once.

    The test sets are the first `eval_meshes` meshes of each split in manifest order
    (all when `None`).
    """
    from dmd_jax.data import load_dataset
    from dmd_jax.pipeline import make_examples

    ds = load_dataset(data_dir)
    train = make_examples(ds.arrays("train"))
    if not train:
        raise ValueError(f"{data_dir}: the training split is empty")
    evals = {}
    for split in ("test_intra", "test_inter"):
        records = ds.split(split)
        if eval_meshes is not None:
            records = records[:eval_meshes]
        evals[split] = make_examples([r.load() for r in records])
    if not any(evals.values()):
        raise ValueError(f"{data_dir}: no test meshes")
    return train, evals


@functools.lru_cache(maxsize=1)
def _calibration_terms():
    import jax

    from dmd_jax import losses

    def terms(noisy, clean, faces, vertex_mask, face_mask):
        h, g = losses.curvature_terms(noisy, clean, faces, vertex_mask=vertex_mask)
        return h, g, losses.normal_loss(noisy, clean, faces, face_mask=face_mask)

    return jax.jit(terms)


def calibrate_curvature(examples, *, seed: int = 0, max_meshes: int = CALIBRATION_MESHES):
    """γ_H, γ_G that put the curvature loss on the normal loss's scale, for this data.

    For the first `max_meshes` training meshes under the training noise (mixed kinds and
    levels, random rotation; keys from `seed`), the unweighted curvature terms `L_H`,
    `L_G` and the normal loss `L_N` (radians) of the noisy mesh against the clean one
    are computed; then `γ_H = ½ median(L_N) / median(L_H)` and likewise `γ_G`, rounded
    to two significant digits, so each curvature term contributes half the normal loss
    for the median mesh. The paper chose its γ (1e-6, 1) "based on distribution of
    objects in our dataset" without saying how; this is our reading of that procedure.

    Returns:
      `{"gamma_h", "gamma_g", "median_l_h", "median_l_g", "median_l_n", "n_meshes"}`.
    """
    import jax

    from dmd_jax.config import NoiseConfig
    from dmd_jax.pipeline import collate, corrupt

    terms = _calibration_terms()
    lh, lg, ln = [], [], []
    base = jax.random.PRNGKey(seed)
    for i, ex in enumerate(examples[:max_meshes]):
        noisy, clean, _ = corrupt(
            jax.random.fold_in(base, i), ex.vertices, ex.faces, rotate=True, noise=NoiseConfig()
        )
        # Padded to the training buckets, so the terms compile once per bucket, not per mesh.
        b = collate([noisy], [clean], [ex.graph])
        g = b.graph
        h, gg, n = terms(b.noisy, b.clean, g.faces, g.vertex_mask, g.face_mask)
        lh.append(float(h))
        lg.append(float(gg))
        ln.append(float(n))
    if not lh:
        raise ValueError("calibrate_curvature needs at least one mesh")
    med = {k: float(np.median(v)) for k, v in (("h", lh), ("g", lg), ("n", ln))}

    def two_digits(x):
        return float(f"{x:.2g}")

    return {
        "gamma_h": two_digits(0.5 * med["n"] / med["h"]),
        "gamma_g": two_digits(0.5 * med["n"] / med["g"]),
        "median_l_h": med["h"],
        "median_l_g": med["g"],
        "median_l_n": med["n"],
        "n_meshes": len(lh),
        "seed": seed,
    }


def ensure_calibration(data_dir, train_examples) -> dict:
    """`calibrate_curvature` of the dataset, computed once and cached next to it."""
    path = Path(data_dir) / CALIBRATION_FILE
    if path.is_file():
        return _read_json(path)
    cal = calibrate_curvature(train_examples)
    _write_json(path, cal)
    return cal


# --------------------------------------------------------------------------------------
# Evaluations
# --------------------------------------------------------------------------------------


# --------------------------------------------------------------------------------------
# Jobs
# --------------------------------------------------------------------------------------


def _train_members(job: dict, members: list[dict], train_ex, evals, log) -> None:
    """Trains (or resumes) the members of a row that have no `train_metrics.json` yet,
    their seeds side by side (`multiseed.train_seeds`), and writes one per member.

    Members that resume from different steps (one was trained alone earlier) train in
    separate groups, each group in one program. (`run_job` passes the row's seeds in
    groups of the job's `seeds_together`.)
    """
    from dmd_jax.config import ExperimentConfig
    from experiments.multiseed import resume_step, train_seeds

    out_dir = Path(job["out_dir"])
    todo = [m for m in members if not (out_dir / m["home"] / "train_metrics.json").is_file()]
    groups: dict[int, list[dict]] = {}
    for m in todo:
        groups.setdefault(resume_step(out_dir / m["home"]), []).append(m)
    for start, group in sorted(groups.items()):
        cfgs = [ExperimentConfig.from_dict(m["config"]) for m in group]
        homes = [out_dir / m["home"] for m in group]
        t0, c0 = time.time(), time.process_time()
        results = train_seeds(
            cfgs,
            train_ex,
            homes,
            eval_sets=evals,
            progress=job["progress"],
            desc=job["label"],
            eval_seed=EVAL_SEED,
        )
        wall, cpu = time.time() - t0, time.process_time() - c0
        times = results[0]["step_times"]
        host = host_info()
        for cfg, home, res in zip(cfgs, homes, results, strict=True):
            metrics, per_mesh = res["metrics"], res["per_mesh"]
            latest = home / "checkpoints" / "latest"
            if not metrics and resume_step(home):
                # Diverged after a checkpoint: evaluate the last saved state.
                metrics, per_mesh = evaluate_checkpoint(cfg, latest, evals)
            out = {
                "status": res["status"],
                "error": res["error"],
                "metrics": metrics,
                "per_mesh": per_mesh,
                "train": {
                    "steps": cfg.train.steps,
                    "final_step": res["step"],
                    "resumed_from": res["resumed_from"],
                    # The group's time, shared evenly: sums over runs stay the sweep's.
                    "wall_s": round(wall / len(group), 2),
                    "cpu_s": round(cpu / len(group), 2),
                    "group_wall_s": round(wall, 2),
                    "group_seeds": len(group),
                    "median_step_s": float(np.median(times)) if times else None,
                    "compiles": res["compiles"],
                },
                "host": host,
            }
            _write_json(home / "train_metrics.json", out)
        log(
            f"trained {job['label']}: seeds {[c.train.seed for c in cfgs]} together, "
            f"{cfgs[0].train.steps} steps"
            + (f", resumed from step {start}" if start else "")
            + f", {wall:.1f} s wall, {cpu:.1f} s CPU"
            + (f", median step {np.median(times) * 1e3:.0f} ms" if times else "")
            + "; "
            + ", ".join(
                f"seed {c.train.seed} {r['status']}" for c, r in zip(cfgs, results, strict=True)
            )
        )


def _bundle(cfg, home: Path):
    from dmd_jax.checkpoints import load_model

    # The checkpoint carries the run's config; `cfg` names the run it must be.
    bundle = load_model(home / "checkpoints" / "latest")
    return bundle._replace(config=cfg, meta={"source": str(home)})


def run_job(job: dict) -> dict:
    """One row of a study at every seed: train its seeds together (or reuse finished
    models), then evaluate every pending run that uses them.

    `job` is plain JSON (it crosses process boundaries): `out_dir`, `data_dir`,
    `eval_meshes`, `preset`, `label`, `progress`, and `members`, one per seed: `home`
    (relative run dir of its training), `config`, `runs` (its pending runs as
    `_spec_to_json`).
    """
    messages: list[str] = []

    def log(msg):
        messages.append(msg)

    train_ex, evals = load_examples(job["data_dir"], job["eval_meshes"])
    members = job["members"]
    # Each group of seeds is evaluated as soon as it is trained, so a sweep stopped
    # inside a row keeps (and can commit) the seeds it finished.
    size = job.get("seeds_together") or len(members) or 1
    trains = []
    for i in range(0, len(members), size):
        group = members[i : i + size]
        _train_members(job, group, train_ex, evals, log)
        trains += [_evaluate_member(job, member, evals, log) for member in group]
    return {"label": job["label"], "messages": messages, "train": trains}


def _evaluate_member(job: dict, member: dict, evals, log) -> dict:
    """Writes the `metrics.json` of every pending run of one trained seed."""
    from dmd_jax.config import ExperimentConfig

    out_dir = Path(job["out_dir"])
    home = out_dir / member["home"]
    cfg = ExperimentConfig.from_dict(member["config"])
    trained = _read_json(home / "train_metrics.json")
    test_meshes = list(evals["test_intra"]) + list(evals["test_inter"])
    bundle = None
    for spec in member["runs"]:
        run_dir = out_dir / spec["study"] / spec["run_id"]
        run_dir.mkdir(parents=True, exist_ok=True)
        run_cfg = ExperimentConfig.from_dict(spec["config"])
        _write_json(run_dir / "config.json", run_cfg.to_dict())
        ev = spec["evaluation"]
        t0 = time.time()
        metrics: dict[str, Any] = {}
        per_mesh: dict[str, list[float]] = dict(trained.get("per_mesh", {}))
        status = trained["status"]
        has_ckpt = (home / "checkpoints" / "latest").is_dir()
        if ev["kind"] == "test":
            metrics = dict(trained["metrics"])
        elif has_ckpt:
            bundle = bundle or _bundle(cfg, home)
            if ev["kind"] == "noise":
                metrics = noise_evaluation(bundle, test_meshes, ev["noise_kind"], ev["level"])
                per_mesh = metrics.pop("per_mesh")
            elif ev["kind"] == "rotation":
                metrics = rotation_evaluation(bundle, test_meshes, gamma=ev["gamma"])
                per_mesh = metrics.pop("per_mesh")
                metrics.update({f"model/{k}": v for k, v in trained["metrics"].items()})
            else:
                raise ValueError(f"unknown evaluation kind {ev['kind']!r}")
        elif status == "ok":
            raise FileNotFoundError(
                f"{home}/checkpoints: the trained model is gone (clean_checkpoints?); delete "
                f"{home}/train_metrics.json to train it again"
            )
        eval_wall = time.time() - t0
        finite = all(math.isfinite(v) for v in metrics.values() if isinstance(v, float))
        record = {
            "preset": job["preset"],
            "study": spec["study"],
            "row": spec["row"],
            "seed": spec["seed"],
            "run_id": spec["run_id"],
            "config_hash": spec["train_hash"],
            "trained_in": member["home"],
            "status": status if finite else "non-finite",
            "error": trained.get("error"),
            "evaluation": ev,
            "metrics": metrics,
            # One value per test mesh, in the order of the test sets (test-intra, then
            # test-inter): what the paired bootstrap of `aggregate` resamples.
            "per_mesh": per_mesh,
            "train": trained["train"],
            "eval_wall_s": round(eval_wall, 2),
            "host": trained["host"],
        }
        rel = f"{spec['study']}/{spec['run_id']}"
        lines = [
            f"run {rel}: study {spec['study']}, row {spec['row']!r}, seed {spec['seed']}, "
            f"preset {job['preset']}",
            f"config hash {spec['train_hash']}; "
            + (
                "trained in this directory"
                if rel == member["home"]
                else f"reuses the model trained in {member['home']}"
            ),
            f"training: {trained['status']}, {trained['train']['steps']} steps, "
            f"{trained['train']['wall_s']} s wall, {trained['train']['cpu_s']} s CPU (its "
            f"share of {trained['train'].get('group_seeds', 1)} seeds trained together)"
            + (
                f" (resumed from step {trained['train']['resumed_from']})"
                if trained["train"].get("resumed_from")
                else ""
            ),
            f"evaluation {ev['kind']}: {eval_wall:.1f} s wall",
            f"host: {trained['host']['platform']}, {trained['host']['cpu_count']} CPUs, "
            f"jax {trained['host']['jax']} ({trained['host']['backend']}), "
            f"XLA_FLAGS={trained['host']['xla_flags']!r}",
        ]
        (run_dir / "run.log").write_text("\n".join(lines) + "\n")
        _write_json(run_dir / "metrics.json", record)
        log(f"finished {rel} ({record['status']}, evaluation {eval_wall:.1f} s)")
    return trained["train"]


# --------------------------------------------------------------------------------------
# Sweep
# --------------------------------------------------------------------------------------


class _Log:
    def __init__(self, path: Path, echo: bool):
        self.path, self.echo = path, echo

    def __call__(self, msg: str) -> None:
        line = f"{time.strftime('%Y-%m-%d %H:%M:%S')} {msg}"
        with open(self.path, "a") as fh:
            fh.write(line + "\n")
        if self.echo:
            from tqdm.auto import tqdm

            tqdm.write(line)


def run_sweep(
    p: st.AblatePreset | str,
    out_dir,
    data_dir,
    *,
    studies: Sequence[str] | None = None,
    seeds: Sequence[int] | None = None,
    workers: int | None = None,
    progress: bool = True,
    aggregate: bool = True,
    echo: bool = True,
) -> dict:
    """Runs (or resumes) every run of `studies` at preset `p`; returns a summary.

    Args:
      p: an `AblatePreset` or a preset name.
      out_dir: results directory.
      data_dir: dataset cache (generated on first use).
      studies: study keys (default: the preset's, `None` there: all).
      seeds: run only these seeds now (default: the preset's). The plan (`plan.json`,
        what the tables are made of) keeps every seed of the preset and adds these, so a
        sweep run seed by seed, over sessions, aggregates all of them.
      workers: parallel training processes (default: the preset's).
      progress: progress bars.
      aggregate: write the tables, plots and README afterwards.
      echo: print log lines (they always go to `out_dir/ablate.log`).
    """
    p = st.get_preset(p) if isinstance(p, str) else p
    studies = studies or p.studies
    p = p.with_seeds(seeds)
    apply_xla_opt_level(p.xla_opt_level)
    if (workers or p.workers) > 1:
        # The worker processes share one accelerator: each preallocating most of its
        # memory (JAX's default on GPU) would leave the second none. No effect on CPU.
        os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
    if p.jax_cache:
        enable_compilation_cache()
    t0 = time.time()
    out_dir, data_dir = Path(out_dir), Path(data_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    log = _Log(out_dir / "ablate.log", echo)
    log(
        f"preset {p.name}: {p.description}; studies {', '.join(studies or st.STUDY_KEYS)}"
        + (f"; seeds {', '.join(map(str, seeds))} of {list(p.seeds)}" if seeds else "")
    )
    ds = ensure_dataset(p, data_dir, progress=progress)
    log(f"dataset {data_dir}: {ds.counts()}")
    train_ex, evals = load_examples(str(data_dir), p.eval_meshes)
    gammas = ensure_calibration(data_dir, train_ex) if p.calibrate_curvature else None
    if gammas:
        log(f"curvature calibration: gamma_h={gammas['gamma_h']:g}, gamma_g={gammas['gamma_g']:g}")
    base = st.base_config(p, gammas)
    # The reference rows (Taubin, BNF, the untrained model) only feed the tables: they are
    # computed in this process while the workers train (~10 s of the smoke sweep's
    # compiling, no longer ahead of the first job).
    references = concurrent.futures.ThreadPoolExecutor(max_workers=1)
    refs_done = references.submit(ensure_references, out_dir, base, evals)
    all_runs = st.plan(p, base, out_dir=out_dir)
    _write_json(
        out_dir / "plan.json",
        {
            "preset": p.to_dict(),
            "base_config": base.to_dict(),
            "calibration": gammas,
            "runs": [
                {k: v for k, v in _spec_to_json(r).items() if k != "config"} for r in all_runs
            ],
        },
    )
    runs = [
        r
        for r in all_runs
        if (studies is None or r.study in studies) and (not seeds or r.seed in seeds)
    ]
    reuse_finished(runs, all_runs, out_dir, log)
    jobs = make_jobs(
        runs,
        out_dir,
        data_dir=data_dir,
        preset_name=p.name,
        eval_meshes=p.eval_meshes,
        progress=progress and (workers or p.workers) <= 1,
        seeds_together=p.seeds_together,
    )
    n_done = len(runs) - sum(len(m["runs"]) for j in jobs for m in j["members"])
    log(
        f"{len(runs)} runs, {n_done} already finished; {len(jobs)} jobs (rows, seeds "
        f"trained together) for {len(st.training_homes(runs))} distinct trainings"
    )
    try:
        failures = _execute(jobs, workers or p.workers, log, progress)
    finally:
        references.shutdown(wait=True)
    refs_done.result()  # raises what computing the references raised
    wall = time.time() - t0
    usage = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = sum(u.ru_utime + u.ru_stime for u in usage)
    argv = list(sys.argv)
    if argv and argv[0].endswith("__main__.py"):
        argv[0] = "python -m experiments"
    session = {
        "command": " ".join(argv),
        "start": time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(t0)),
        "wall_s": round(wall, 1),
        "cpu_s": round(cpu, 1),
        "studies": list(studies or st.STUDY_KEYS),
        "jobs": len(jobs),
        "failures": failures,
        "workers": workers or p.workers,
        "load_average": list(os.getloadavg()),
        "host": host_info(),
    }
    sessions_path = out_dir / "sessions.json"
    sessions = _read_json(sessions_path) if sessions_path.is_file() else []
    _write_json(sessions_path, [*sessions, session])
    log(f"done: {len(jobs)} jobs in {wall:.1f} s wall, {cpu:.1f} s CPU; {len(failures)} failed")
    if aggregate:
        from experiments import aggregate as agg

        agg.aggregate(out_dir)
        log(f"tables, plots and README written to {out_dir}")
    return session


def run_jobs(jobs: Sequence[dict], queue=None) -> list[dict]:
    """Runs jobs one after the other in this process (a `pack_jobs` task).

    Each outcome, `{"index", "result"}` or `{"index", "error"}` (the exception as text:
    one broken run must not end a sweep of hours), is put on `queue` as soon as its
    job ends, so the sweep's log and remaining time follow job by job.
    """
    outcomes = []
    for job in jobs:
        try:
            outcome = {"index": job["index"], "result": run_job(job)}
        except Exception as exc:
            outcome = {"index": job["index"], "error": f"{type(exc).__name__}: {exc}"}
        if queue is not None:
            queue.put(outcome)
        outcomes.append(outcome)
    return outcomes


def _execute(jobs: list[dict], workers: int, log: Callable, progress: bool) -> list[str]:
    """Runs the jobs (in `workers` processes); a bar and log lines give the remaining time.

    With more than one worker the jobs go in `pack_jobs` tasks, so that rows sharing a
    compiled program meet in one process. The estimate weighs every job by its `cost`
    (training steps): remaining = elapsed × (cost left / cost done), so it is rough
    until the first rows have finished.
    """
    import queue as queue_lib

    from tqdm.auto import tqdm

    failures: list[str] = []
    workers = max(1, min(int(workers), len(jobs) or 1))
    total = sum(j["cost"] for j in jobs) or 1.0
    done = {"cost": 0.0, "jobs": 0}
    t0 = time.time()
    for i, job in enumerate(jobs):
        job["index"] = i
    with tqdm(
        total=round(total), desc="ablate", unit="step", disable=not progress, position=0
    ) as bar:

        def finished(job, result=None, error=None):
            if error is not None:
                failures.append(f"{job['label']}: {error}")
                log(f"FAILED {job['label']}: {error}")
            else:
                for msg in result["messages"]:
                    log(msg)
            done["cost"] += job["cost"]
            done["jobs"] += 1
            elapsed = time.time() - t0
            left = elapsed * (total - done["cost"]) / max(done["cost"], 1e-9)
            log(
                f"progress: {done['jobs']}/{len(jobs)} rows, {100 * done['cost'] / total:.0f} % "
                f"of the training steps, {elapsed / 60:.1f} min elapsed, about "
                f"{left / 60:.0f} min left"
            )
            bar.update(round(done["cost"]) - bar.n)

        def report(outcome):
            job = jobs[outcome["index"]]
            finished(job, outcome.get("result"), outcome.get("error"))

        if workers == 1:
            for outcome in run_jobs(jobs):
                report(outcome)
            return failures
        for job in jobs:
            job["programs"] = job_programs(job)
        tasks = pack_jobs(jobs, workers)
        log(
            f"{len(jobs)} jobs in {len(tasks)} tasks for {workers} processes (rows that "
            f"share a compiled program in one), "
            f"{len({p for j in jobs for p in j['programs']})} distinct programs"
        )
        ctx = multiprocessing.get_context("spawn")
        reported: set[int] = set()
        with (
            ctx.Manager() as manager,
            concurrent.futures.ProcessPoolExecutor(workers, mp_context=ctx) as pool,
        ):
            outcomes = manager.Queue()
            futures = {pool.submit(run_jobs, task, outcomes): task for task in tasks}
            while len(reported) < len(jobs):
                try:
                    outcome = outcomes.get(timeout=1.0)
                except queue_lib.Empty:
                    # Everything a finished task put is in the queue already: all done
                    # and empty means the rest died with their process.
                    if all(f.done() for f in futures):
                        break
                    continue
                reported.add(outcome["index"])
                report(outcome)
            for fut, task in futures.items():
                exc = fut.exception()
                why = f"{type(exc).__name__}: {exc}" if exc else "no result from its process"
                for job in task:
                    if job["index"] not in reported:
                        reported.add(job["index"])
                        finished(job, error=why)
    return failures


def clean_checkpoints(out_dir) -> int:
    """Removes every `checkpoints/` folder under `out_dir` (after a finished sweep);
    returns how many were removed."""
    n = 0
    for ckpt in Path(out_dir).glob("*/*/checkpoints"):
        shutil.rmtree(ckpt)
        n += 1
    return n
