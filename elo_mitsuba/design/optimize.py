"""The optimiser: a Pareto front of detector systems, each evaluation a task on the sweeps' Dask engine.

Why Optuna: it is maintained, its samplers are multi-objective with constraints (NSGA-II, and the
multi-objective TPE that needs far fewer evaluations at budgets of ~100), its ask-and-tell
interface lets every evaluation be a Dask task that this client collects, and its journal storage
(an append-only file, no database server) keeps the optimiser's state across a killed run. pymoo
has the algorithms but no storage to resume from; nevergrad and CMA-ES optimise one weighted sum
(or need one to rank), not a front.

Flow per batch: ask ``batch`` trials (their parameters), submit one task per design
(:func:`~.evaluate.evaluate_design`), append each result to ``OUT.zarr/.optimize/evaluations.jsonl``
(on disk before anything else), then tell the optimiser. A killed run resumes from these two
files: a trial the journal holds as running whose result the log has is told from the log (not
evaluated again); one without a result is evaluated; completed trials count towards ``trials``.
The dataset (every evaluated design, :mod:`.store`) is rewritten from the log at most every
:data:`WRITE_EVERY_S` seconds and at the end.

Before any work: the spec is checked (:func:`~.spec.load_spec`), and so is the design space
(:func:`check_design_space`): bounds no feasible design lies in are refused with one line. Then the
run's cost is estimated (:func:`estimate`) and checked by :func:`elo_mitsuba.budget.check_work`, the
rule of render and sweep: above its ``REFUSE_SECONDS`` (4 h) refused unless ``force`` (CLI
``--yes``), memory beyond what is available always; above ``NOTE_SECONDS`` the estimate is printed.
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import EloInputError
from . import store
from .evaluate import evaluate_design
from .geometry import CONSTRAINTS, design_discs, violations
from .spec import OptimizeSpec, load_spec

#: Random designs (and the bounds' corners) tried by :func:`check_design_space`.
PROBE_DESIGNS = 1000
#: The dataset is rewritten at most this often (s) while running, and at the end.
WRITE_EVERY_S = 5.0
#: Study name in the journal.
STUDY = "elo-optimize"
#: Modules the optimiser needs (the ``sweep`` extra).
MODULES = ("dask", "distributed", "xarray", "zarr", "optuna")

# ---- the cost of a run (:func:`estimate`) ----------------------------------------------------------
# Measured on this project's 2-core machine (llvm_ad_mono, another process busy on the cores at
# times), by timing small runs: optimize(workers=0) of 400 designs, count 4, 3 x 3 field points,
# batch 8, took 0.128 s (random), 0.128 s (tpe), 0.116 s (nsga2) per design, of which
# evaluate_design 0.11-0.13 s; evaluate_design alone (CPU time, mean of 40 random designs) at
# count 3/4/8/16 and 1 x 1 field points 0.11/0.11/0.23/0.42 s, at count 4 with 32^2/64^2 points
# 0.20/0.27 s, count 8 with 32^2 points 0.31 s (most of it Dr.Jit tracing each design's kernel).
#: evaluate_design: seconds per detector, and per detector and field point (grid^2).
EVAL_SECONDS_PER_DETECTOR = 0.03
EVAL_SECONDS_PER_DETECTOR_POINT = 1e-5
#: The objective e2_share: seconds per design besides its samples (moving the four discs, the
#: render's set-up; 0.054-0.065 s at 8^2-32^2 px and 64-1024 spp), and samples (px x spp x 2
#: events) per second on 2 cores (128^2 px at 256 spp: 0.77 s; 64^2 at 1024: 0.62 s).
E2_SECONDS_PER_DESIGN = 0.06
E2_SAMPLES_PER_SECOND_2_CORES = 1.2e7
#: Asking and telling the optimiser, per design: Optuna's samplers with this journal storage and
#: no evaluation (3000 designs, batch 8): random 0.002 s, NSGA-II 0.004 s; the TPE's grows with
#: the designs before it, 0.002 s + TPE_SECONDS_PER_EARLIER_DESIGN x n (n = 600/3000/6000: 0.008/
#: 0.029/0.076 s), with 3 free parameters, and (P + 4) / 7 times that with P free parameters
#: (24: 3.7 times in all for 1500 designs).
SAMPLER_SECONDS = {"random": 0.002, "grid": 0.002, "nsga2": 0.004, "tpe": 0.002}
TPE_SECONDS_PER_EARLIER_DESIGN = 1.2e-5
#: store.write_dataset, every WRITE_EVERY_S and at the end: WRITE_SECONDS (Zarr, 0.7 s at 1000
#: designs) plus its Pareto front, which compares every pair of n designs: PARETO_SECONDS_PER_PAIR
#: x n^2 (0.68 s at 4000, 2.7 s at 8000) and (objectives + 2) x n^2 bytes at its peak (4.0 n^2
#: measured with 2 objectives). The whole model against runs whose evaluation was a 0.01 s sleep
#: (random, batch 8): 2000 designs 30 s (estimate 29 s), 10000 designs 193 s (175 s).
WRITE_SECONDS = 0.7
PARETO_SECONDS_PER_PAIR = 4.2e-8


@dataclass
class OptimizeSummary:
    """What a run did: the store, trials in all, evaluated now, told from a killed run's log,
    seconds, workers, ``created``/``resumed``, designs on the front."""

    path: Path
    trials: int
    evaluated: int
    recovered: int
    seconds: float
    workers: int
    state: str
    front: int


def design_params(spec: OptimizeSpec, values: dict, count: int) -> dict:
    """A design's full parameters: the optimiser's ``values`` plus the spec's fixed ones."""
    return {n: float(values[n]) if n in values else spec.bound(n)[0] for n in spec.parameter_names(count)}


def check_design_space(spec: OptimizeSpec, n: int = PROBE_DESIGNS, seed: int = 0) -> None:
    """Refuse (one line) bounds within which no design meets the constraints: ``n`` random designs
    and the corners of the bounds are checked (geometry only, ~1 ms each).

    Examples
    --------
    Detectors whose centres would be 560-700 mm high, in a chamber 550 mm high:

    >>> check_design_space(load_spec({"parameters": {"dh": [560.0, 700.0]}}))
    Traceback (most recent call last):
    ...
    elo_mitsuba.errors.EloInputError: spec: no design within the bounds meets the constraints (1000 random designs and the corners tried); the closest violates 'chamber' by 21 mm: widen [parameters] or lower constraints.clearance (10 mm)
    """
    rng = np.random.default_rng(seed)
    m = spec.metric
    best = (math.inf, None)
    for i in range(n + 2 ** 5 * len(spec.counts)):
        count = spec.counts[i % len(spec.counts)]
        names = spec.parameter_names(count)
        if i < n:
            vals = {p: rng.uniform(*spec.bound(p)) for p in names}
        else:  # a corner of the (symmetric) bounds
            j = i - n
            vals = {p: spec.bound(p)[(j >> (b % 5)) & 1] for b, p in enumerate(names)}
        v = violations(design_discs(vals, count, spec.symmetric), field_mm=m["field"], work_distance_mm=m["wd"],
                       clearance=spec.clearance)
        worst = max(v.values())
        if worst <= 0:
            return
        if sum(v.values()) < best[0]:
            best = (sum(v.values()), max(v, key=v.get), worst)
    raise EloInputError(f"{spec.source}: no design within the bounds meets the constraints ({n} random designs and "
                        f"the corners tried); the closest violates {best[1]!r} by {best[2]:.0f} mm: widen [parameters] "
                        f"or lower constraints.clearance ({spec.clearance:g} mm)")


def estimate(spec: OptimizeSpec, designs: int, *, done: int = 0, parallel: int = 1) -> dict:
    """The estimated cost of evaluating ``designs`` designs after ``done`` stored ones, with
    ``parallel`` evaluations at a time (the constants above: measured, meant to be right within a
    factor of two): ``seconds`` (the run on this machine), ``memory_bytes`` (its peak) and
    ``per_design`` (seconds of one evaluation).

    Examples
    --------
    >>> e = estimate(load_spec({"metric": {"grid": 3}, "optimizer": {"sampler": "random"}}), 1000)
    >>> round(e["per_design"], 3), 100 < e["seconds"] < 300
    (0.12, True)
    """
    import os

    from ..budget import BASE_BYTES

    m, opt = spec.metric, spec.optimizer
    count = max(spec.counts)
    per_design = count * (EVAL_SECONDS_PER_DETECTOR + EVAL_SECONDS_PER_DETECTOR_POINT * m["grid"] ** 2)
    if "e2_share" in spec.objectives:
        cores = max(1, os.cpu_count() or 1)
        samples = spec.render["resolution"] ** 2 * spec.render["spp"] * 2
        per_design += E2_SECONDS_PER_DESIGN + samples / (E2_SAMPLES_PER_SECOND_2_CORES * cores / 2)
    n0, n1 = int(done), int(done) + int(designs)
    ask = SAMPLER_SECONDS[opt["sampler"]] * designs
    if opt["sampler"] == "tpe":
        free = max(len(spec.free_parameters(c)) for c in spec.counts)
        ask = (ask + TPE_SECONDS_PER_EARLIER_DESIGN * (n1 ** 2 - n0 ** 2) / 2) * (free + 4) / 7
    loop = designs * per_design / max(1, int(parallel)) + ask
    # a rewrite every WRITE_EVERY_S of the loop, of the designs stored by then (the mean of n^2
    # over n0..n1), and one at the end
    mean_pairs = (n1 ** 2 + n1 * n0 + n0 ** 2) / 3
    writes = loop / WRITE_EVERY_S * (WRITE_SECONDS + PARETO_SECONDS_PER_PAIR * mean_pairs)
    last = WRITE_SECONDS + PARETO_SECONDS_PER_PAIR * n1 ** 2
    memory = BASE_BYTES + (len(spec.objectives) + 2) * n1 ** 2
    return {"seconds": loop + writes + last, "memory_bytes": memory, "per_design": per_design}


def _check_cost(spec: OptimizeSpec, path: Path, target: int, *, overwrite: bool, parallel: int | None,
                max_evaluations: int | None, force: bool, progress: bool | None) -> None:
    """Refuse a run whose estimate is out of bounds (:func:`elo_mitsuba.budget.check_work`), before
    the store is created; print the estimate of a long one (unless ``progress`` is False).
    ``parallel``: local workers (0: in this process), None for a scheduler's (then the batch)."""
    from ..budget import NOTE_SECONDS, check_work, human_seconds

    done = 0
    if not overwrite and (store.state_dir(path) / store.LOG).is_file():  # resumed: what is stored is not redone
        done = len(store.read_records(path))
    designs = max(0, target - done)
    if max_evaluations is not None:
        designs = min(designs, max_evaluations)
    batch = spec.optimizer["batch"]
    at_once = batch if parallel is None else max(1, min(parallel, batch))
    est = estimate(spec, designs, done=done, parallel=at_once)
    m = spec.metric
    renders = (f", e2_share rendering {spec.render['resolution']}^2 px at {spec.render['spp']} spp"
               if "e2_share" in spec.objectives else "")
    what = (f"{spec.source}: {designs} designs ({spec.optimizer['sampler']}, count "
            f"{'/'.join(str(c) for c in spec.counts)}, {m['grid']}x{m['grid']} field points{renders}; about "
            f"{est['per_design']:.2g} s each, {at_once} at a time{' at most' if parallel is None else ''})")
    check_work(est["seconds"], est["memory_bytes"], force, what=what,
               hint="lower optimizer.trials, or run them in parts with --stop-after (time and memory grow with "
                    "the square of the designs: the optimiser and the store's Pareto front compare them)")
    if est["seconds"] > NOTE_SECONDS and progress is not False:
        print(f"elo-mitsuba: note: {what} take about {human_seconds(est['seconds'])} on this machine (estimate; "
              "Ctrl-C stops, re-running resumes)", file=sys.stderr, flush=True)


def _sampler(spec: OptimizeSpec):
    import warnings

    import optuna

    # Optuna 5 deprecates constraints_func (removal in 7; pyproject pins < 7) for
    # Trial.set_constraint, which a trial told after a restart (no Trial object) cannot call
    warnings.filterwarnings("ignore", message=".*constraints_func.*", category=FutureWarning)

    opt = spec.optimizer
    m = spec.metric

    def constraints(trial):
        # from the parameters alone (geometry): also for a trial told after a restart
        count = int(trial.params.get("count", spec.counts[0]))
        v = violations(design_discs(design_params(spec, trial.params, count), count, spec.symmetric),
                       field_mm=m["field"], work_distance_mm=m["wd"], clearance=spec.clearance)
        return [v[c] for c in CONSTRAINTS]

    if opt["sampler"] == "nsga2":
        return optuna.samplers.NSGAIISampler(population_size=max(opt["batch"], 4), seed=opt["seed"],
                                             constraints_func=constraints)
    if opt["sampler"] == "random":
        return optuna.samplers.RandomSampler(seed=opt["seed"])
    if opt["sampler"] == "grid":
        # the grid's points are enqueued when the study is created (:func:`optimize`): Optuna's
        # GridSampler stops its study from inside tell() when the grid is exhausted, which the
        # ask-and-tell interface refuses with an error
        return optuna.samplers.RandomSampler(seed=opt["seed"])
    return optuna.samplers.TPESampler(seed=opt["seed"], multivariate=True, constant_liar=True,
                                      n_startup_trials=min(20, max(opt["trials"] // 5, 5)),
                                      constraints_func=constraints)


def grid_space(spec: OptimizeSpec) -> dict:
    """The grid of ``sampler = "grid"``: ``grid_points`` values per free parameter (and the counts).

    Examples
    --------
    >>> g = grid_space(load_spec({"parameters": {"radius": 25.0}, "optimizer": {"sampler": "grid", "grid_points": 3}}))
    >>> {k: [float(x) for x in v] for k, v in g.items()}
    {'dh': [60.0, 290.0, 520.0], 'dw': [60.0, 195.0, 330.0]}
    """
    out = {}
    if len(spec.counts) > 1:
        out["count"] = list(spec.counts)
    for p in spec.free_parameters(max(spec.counts)):
        out[p] = [float(x) for x in np.linspace(*spec.bound(p), spec.optimizer["grid_points"])]
    return out


def _suggest(spec: OptimizeSpec, trial) -> tuple[dict, int]:
    count = trial.suggest_categorical("count", list(spec.counts)) if len(spec.counts) > 1 else spec.counts[0]
    for p in spec.free_parameters(count):
        trial.suggest_float(p, *spec.bound(p))
    return design_params(spec, trial.params, count), int(count)


def _record(spec, number, params, count, result) -> dict:
    feasible = max(result["violations"].values()) <= 0
    return {"trial": int(number), "count": count, "params": params, "metrics": result["metrics"],
            "violations": result["violations"], "seconds": result["seconds"], "feasible": bool(feasible)}


def optimize(spec, output, *, workers: int | None = None, scheduler: str | None = None,
             threads_per_worker: int | None = None, overwrite: bool = False, progress: bool | None = None,
             max_evaluations: int | None = None, force: bool = False) -> OptimizeSummary:
    """Search the spec's design space for the Pareto front of its objectives.

    Parameters
    ----------
    spec : str, Path, dict or OptimizeSpec
        The optimiser spec (:mod:`.spec`).
    output : str or Path
        The ``.zarr`` store; an existing store of the same spec is resumed.
    workers : int, optional
        Local Dask worker processes (default 1; 0 = in this process, without Dask).
    scheduler : str, optional
        A running Dask scheduler's address (``tcp://host:port``) or scheduler file.
    threads_per_worker : int, optional
        Dr.Jit threads per worker.
    overwrite : bool
        Replace an optimiser's store of another spec.
    progress : bool, optional
        A progress line on stderr (default: when stderr is a terminal).
    max_evaluations : int, optional
        Stop (resumably) after this many evaluations in this run.
    force : bool
        Start a run estimated (:func:`estimate`) to take longer than
        :data:`~elo_mitsuba.budget.REFUSE_SECONDS` (CLI ``--yes``); memory beyond what is
        available is refused regardless.

    Returns
    -------
    OptimizeSummary

    Examples
    --------
    Six designs of Table 1's kind (only dh and dw free), in this process:

    >>> import tempfile
    >>> spec = {"parameters": {"radius": 25.0}, "metric": {"grid": 2},
    ...         "optimizer": {"trials": 6, "batch": 3, "sampler": "random"}}
    >>> with tempfile.TemporaryDirectory() as d:
    ...     s = optimize(spec, Path(d) / "o.zarr", workers=0, progress=False)
    ...     ds = store.read_designs(Path(d) / "o.zarr")
    >>> s.evaluated, s.state, ds.sizes["design"], bool(ds.pareto.any())
    (6, 'created', 6, True)
    """
    from ..sweeps.extra import require
    from ..sweeps.run import check_resources

    require("elo-mitsuba optimize", MODULES)
    workers, address, threads = check_resources(workers, scheduler, threads_per_worker)
    spec = load_spec(spec)
    check_design_space(spec)
    if max_evaluations is not None and (isinstance(max_evaluations, bool) or not isinstance(max_evaluations, int)
                                        or max_evaluations < 1):
        raise EloInputError(f"max_evaluations={max_evaluations!r}; must be a whole number >= 1")
    from ..arguments import flag
    from ..sweeps.store import zarr_path

    force = flag("force", force)
    path = zarr_path(output, "the optimiser")
    target = spec.trials
    if spec.optimizer["sampler"] == "grid":
        target = min(target, math.prod(len(v) for v in grid_space(spec).values()))
    _check_cost(spec, path, target, overwrite=overwrite, parallel=workers if address is None else None,
                max_evaluations=max_evaluations, force=force, progress=progress)
    import optuna
    from optuna.storages import JournalStorage
    from optuna.storages.journal import JournalFileBackend

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    state = store.check_store(path, spec, overwrite=overwrite)
    storage = JournalStorage(JournalFileBackend(str(store.state_dir(path) / "journal.log")))
    study = optuna.create_study(study_name=STUDY, storage=storage, directions=spec.directions,
                                sampler=_sampler(spec), load_if_exists=True)
    if spec.optimizer["sampler"] == "grid":
        import itertools

        space = grid_space(spec)
        points = list(itertools.product(*space.values()))
        if not study.trials:  # a new study: the grid in a fixed order (resumed: its waiting trials)
            for values in points[:target]:
                study.enqueue_trial(dict(zip(space, values)))
    records = {r["trial"]: r for r in store.read_records(path)}
    settings = spec.to_dict()
    show = sys.stderr.isatty() if progress is None else progress
    client = cluster = None
    if workers != 0:
        from ..sweeps.run import connect

        client, cluster = connect(address, workers)
        if address is None:
            from ..sweeps.run import available_cores
            from ..sweeps.worker import set_up

            client.run(set_up, threads or max(1, available_cores() // max(workers, 1)))
    else:
        from ..sweeps.worker import set_up

        set_up(threads)
    t0 = time.perf_counter()
    evaluated = recovered = 0
    last_write = time.monotonic()
    try:
        # a killed run's trials: told from the log if evaluated, else evaluated now
        leftover = []
        for t in study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.RUNNING,)):
            if t.number in records:
                study.tell(t.number, [records[t.number]["metrics"][o] for o in spec.objectives])
                recovered += 1
            else:
                count = int(t.params.get("count", spec.counts[0]))
                names = spec.free_parameters(count)
                if all(n in t.params for n in names):
                    leftover.append((t.number, design_params(spec, t.params, count), count))
                else:  # killed while asking: never evaluated, nothing to keep
                    study.tell(t.number, state=optuna.trial.TrialState.FAIL)
        while True:
            done = sum(t.state == optuna.trial.TrialState.COMPLETE for t in study.get_trials(deepcopy=False))
            want = target - done - len(leftover)
            if max_evaluations is not None:
                want = min(want, max_evaluations - evaluated - len(leftover))
            batch = list(leftover)
            leftover = []
            while want > 0 and len(batch) < spec.optimizer["batch"]:
                trial = study.ask()
                params, count = _suggest(spec, trial)
                batch.append((trial.number, params, count))
                want -= 1
            if not batch:
                break
            if client is None:
                results = [evaluate_design(p, c, settings) for _, p, c in batch]
            else:
                futures = [client.submit(evaluate_design, p, c, settings, pure=False) for _, p, c in batch]
                try:
                    results = client.gather(futures)
                except Exception as exc:  # noqa: BLE001 -- a lost worker or scheduler: one line, resumable
                    from ..errors import EloError

                    raise EloError(f"the Dask cluster failed ({type(exc).__name__}: {' '.join(str(exc).split())[:160]}); "
                                   f"{len(records)} designs are stored: re-run the same command to resume") from None
            new = [_record(spec, n, p, c, r) for (n, p, c), r in zip(batch, results)]
            store.append_records(path, new)  # on disk before the optimiser hears of it
            for r in new:
                records[r["trial"]] = r
                study.tell(r["trial"], [r["metrics"][o] for o in spec.objectives])
            evaluated += len(new)
            if show:
                print(f"\r  {done + len(new)}/{target} designs, {evaluated} evaluated in "
                      f"{time.perf_counter() - t0:.0f} s ", end="", file=sys.stderr, flush=True)
            if time.monotonic() - last_write > WRITE_EVERY_S:
                store.write_dataset(path, records.values(), spec)
                last_write = time.monotonic()
            if max_evaluations is not None and evaluated >= max_evaluations:
                break
        if show:
            print(file=sys.stderr)
        store.write_dataset(path, records.values(), spec)
    finally:
        from ..sweeps.run import disconnect

        disconnect(client, cluster)
    ds = store.read_designs(path)
    return OptimizeSummary(path=path, trials=int(ds.sizes["design"]), evaluated=evaluated, recovered=recovered,
                           seconds=time.perf_counter() - t0, workers=workers or 0, state=state,
                           front=int(ds.pareto.sum()))
