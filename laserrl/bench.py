"""``laserrl-bench``: cavity round trips per second, torch batch vs the scipy reference.

Everything is measured in one run, so the ratios hold on a shared, noisy machine:

* the scipy reference (``laserrl.physics.reference``): one cavity, scipy's Fortran DOP853
  (``scipy.integrate.ode``) per round trip at that integrator's default tolerances (rtol
  1e-6, atol 1e-12), as the paper's public code runs it; the ratios are against this.
  It is timed three times, before, between and after the torch timings, and the ratios
  use the median, so that a passing slowdown of the host during one short timing does
  not move them all;
  For comparison also at ``solve_ivp``'s looser defaults (rtol 1e-3, atol 1e-6);
* the torch solver at the default settings (complex64, ``CavityParams().z_steps``)
  for each batch size, compiled unless ``--no-compile``;
* the FFT-bound estimate: the time of the FFT pairs alone that one round trip needs
  (``fft_pairs_per_round_trip``: one inverse and one forward FFT of both fields per
  Strang step, or per DOP853 stage);
* accuracy: worst relative L2 error of one round trip against the stored
  high-accuracy reference solutions (``laserrl/data/cavity_reference.npz``);
* with ``--compare-coarse-steps N``: the torch solver also with a coarse split-step pass of
  N steps (``CavityParams(z_steps_coarse=N)``; 8 gives the classic (N, 2N) pair (8, 16)), timed in
  alternation with the default at each batch size, and the speed ratio of the two;
* with ``--k-sweep``: instead of the timings, the worst one-round-trip error of the default
  solver (and of the comparison setting) over K in [-0.2, 0.4], several angle sets and sech
  and noise starts, along reference trajectories of ``CavityParams.precise()``
  (``sweep_references``, ``one_round_trip_errors``);
* with ``--processes N``: the whole machine, N processes of one torch thread each
  stepping their own batch at the same time (how the training collectors use a
  multi-core CPU), and for comparison N scipy reference processes at the same time.
  Their rates add up; the workers start together on a barrier and each runs for
  ``--min-seconds``.
"""
from __future__ import annotations

import argparse
import dataclasses
import math
import os
import platform
import statistics
import sys
import time

import numpy as np
import torch

from laserrl.paths import REFERENCE_DATA
from laserrl.physics import CavityParams, noise_fields, round_trip, sech_fields
from laserrl.physics import reference as ref
from laserrl.physics.cavity import fft_pairs_per_round_trip
from laserrl.spawned import spawn_on_barrier

PAPER_ANGLES_DEG = (-24.0, 3.0, 28.0, 88.0)


def _reference_data() -> dict | None:
    if not REFERENCE_DATA.exists():
        return None
    with np.load(REFERENCE_DATA) as d:
        return {k: d[k] for k in d.files}


def _cases(data: dict) -> list[str]:
    return sorted({k.split("/")[0] for k in data if "/" in k})


def _rel_err(u, v, U, V) -> np.ndarray:
    num = np.sqrt((np.abs(u - U) ** 2).sum(-1) + (np.abs(v - V) ** 2).sum(-1))
    return num / np.sqrt((np.abs(U) ** 2).sum(-1) + (np.abs(V) ** 2).sum(-1))


def torch_accuracy(data: dict, params: CavityParams, dtype=torch.complex64, compile: bool = False) -> float:
    """Worst one-round-trip relative error over every stored round trip of every case."""
    worst = 0.0
    for case in _cases(data):
        u = torch.as_tensor(data[f"{case}/u"][:-1]).to(dtype)
        v = torch.as_tensor(data[f"{case}/v"][:-1]).to(dtype)
        ang = torch.deg2rad(torch.as_tensor(data[f"{case}/angles_deg"], dtype=torch.float64)).expand(u.shape[0], 4)
        u1, v1 = round_trip(u, v, ang, float(data[f"{case}/K"]), params, compile=compile)
        err = _rel_err(u1.cpu().numpy(), v1.cpu().numpy(), data[f"{case}/u"][1:], data[f"{case}/v"][1:])
        worst = max(worst, float(err.max()))
    return worst


# --- accuracy sweep over K, angles and start kinds ------------------------------------------
#: K values and angle sets (alpha1, alpha2, alpha3, alpha_p in degrees) of ``--k-sweep``.
SWEEP_K = (-0.2, 0.0, 0.1, 0.2, 0.3, 0.4)
SWEEP_ANGLES_DEG = {
    "alpha1=-24": PAPER_ANGLES_DEG,
    "alpha1=-40": (-40.0, 3.0, 28.0, 88.0),
    "alpha1=-12": (-12.0, 3.0, 28.0, 88.0),
    "four-controller": (15.0, -5.0, 20.0, 84.0),
}
SWEEP_STARTS = ("sech", "noise")


def sweep_references(Ks=SWEEP_K, angles_deg: dict = SWEEP_ANGLES_DEG, starts=SWEEP_STARTS, round_trips: int = 30,
                     seed: int = 0, params: CavityParams | None = None):
    """Reference trajectories, one cavity per (K, angle set, start kind), all in one batch.

    Starts are ``sech_fields`` (the paper's 0.5 sech(t/2)) or ``noise_fields`` (seeded);
    the trajectories have the physics of ``params`` (default: the paper's) and are run at
    ``CavityParams.precise()`` resolution in complex128. Returns (labels [(K, angle name,
    start)], angles (B, 4) rad, K (B,), U, V (B, round_trips + 1, n) complex128 with the
    start at index 0)."""
    base = params or CavityParams()
    numerics = ("z_steps", "z_steps_coarse", "integrator")
    precise = CavityParams.precise(**{f.name: getattr(base, f.name) for f in dataclasses.fields(base)
                                      if f.name not in numerics})
    labels = [(float(K), name, start) for K in Ks for name in angles_deg for start in starts]
    B = len(labels)
    u_s, v_s = sech_fields(B, precise, dtype=torch.complex128)
    u_n, v_n = noise_fields(B, precise, generator=torch.Generator().manual_seed(seed), dtype=torch.complex128)
    noise = torch.tensor([start == "noise" for *_, start in labels])[:, None]
    u, v = torch.where(noise, u_n, u_s), torch.where(noise, v_n, v_s)
    ang = torch.deg2rad(torch.tensor([angles_deg[name] for _, name, _ in labels], dtype=torch.float64))
    K = torch.tensor([k for k, *_ in labels], dtype=torch.float64)
    us, vs = [u], [v]
    for _ in range(round_trips):
        u, v = round_trip(u, v, ang, K, precise)
        us.append(u)
        vs.append(v)
    return labels, ang, K, torch.stack(us, 1), torch.stack(vs, 1)


def one_round_trip_errors(references, params: CavityParams, dtype=torch.complex64, compile: bool = False) -> np.ndarray:
    """(B, R) relative L2 errors of one round trip of ``params`` started from each state of the
    reference trajectories (``sweep_references``) against the reference's next state."""
    _, ang, K, U, V = references
    B, R1, n = U.shape
    R = R1 - 1
    u1, v1 = round_trip(U[:, :-1].reshape(-1, n).to(dtype), V[:, :-1].reshape(-1, n).to(dtype),
                        ang.repeat_interleave(R, 0), K.repeat_interleave(R, 0), params, compile=compile)
    err = _rel_err(u1.to(torch.complex128).numpy(), v1.to(torch.complex128).numpy(),
                   U[:, 1:].reshape(-1, n).numpy(), V[:, 1:].reshape(-1, n).numpy())
    return err.reshape(B, R)


def print_k_sweep(references, settings: dict, out=sys.stdout) -> dict:
    """Markdown tables of the worst one-round-trip error per K for each named params setting:
    of the first round trip from each start kind, of the later round trips per angle set
    (both starts), and of all; returns {setting: {K: worst of all}}."""
    labels = references[0]
    Ks = sorted({k for k, *_ in labels})
    names = list(dict.fromkeys(name for _, name, _ in labels))
    starts = list(dict.fromkeys(start for *_, start in labels))
    rounds = references[3].shape[1] - 1
    worst = {}
    for setting, params in settings.items():
        err = one_round_trip_errors(references, params)
        worst[setting] = {}
        print(f"\nworst one-round-trip error, {setting} (complex64, {rounds} round trips from each start, "
              f"against CavityParams.precise() trajectories):\n", file=out)
        cols = [f"1st trip, {s}" for s in starts] + [f"later, {nm}" for nm in names] + ["all"]
        print("| K | " + " | ".join(cols) + " |", file=out)
        print("|---:|" + "---:|" * len(cols), file=out)
        for K in Ks:
            rows = [i for i, (k, *_) in enumerate(labels) if k == K]
            cells = [err[[i for i in rows if labels[i][2] == s], 0].max() for s in starts]
            cells += [err[[i for i in rows if labels[i][1] == nm], 1:].max() if rounds > 1 else float("nan")
                      for nm in names]
            cells.append(err[rows].max())
            worst[setting][K] = float(err[rows].max())
            print(f"| {K:+.1f} | " + " | ".join(f"{c:.1e}" for c in cells) + " |", file=out)
    return worst


#: (rtol, atol) of the reference the ratios are against (the paper's code), and a looser pair.
PAPER_TOL = (ref.PAPER_RTOL, ref.PAPER_ATOL)
LOOSE_TOL = (1e-3, 1e-6)


def _sci(x: float) -> str:
    """1e-06 -> '1e-6', as the tolerances are written in the docs."""
    mantissa, exponent = f"{x:.0e}".split("e")
    return f"{mantissa}e{int(exponent)}"


SCIPY_PAPER = f"scipy DOP853 (paper's code, rtol {_sci(PAPER_TOL[0])})"
SCIPY_LOOSE = f"scipy DOP853 (rtol {_sci(LOOSE_TOL[0])})"


def scipy_accuracy(data: dict, params: CavityParams, tol=PAPER_TOL, every: int = 4) -> float:
    worst = 0.0
    for case in _cases(data):
        ang = np.deg2rad(data[f"{case}/angles_deg"])
        for j in range(0, len(data[f"{case}/u"]) - 1, every):
            u, v = ref.round_trip(data[f"{case}/u"][j], data[f"{case}/v"][j], ang, float(data[f"{case}/K"]), params, *tol)
            worst = max(worst, float(_rel_err(u, v, data[f"{case}/u"][j + 1], data[f"{case}/v"][j + 1])))
    return worst


def scipy_stepper(params: CavityParams, tol=PAPER_TOL):
    """One cavity of the reference from the paper's sech start: a function doing one round
    trip per call (the transient, then settling, as in the paper's code)."""
    u, v = sech_fields(1, params, dtype=torch.complex128)
    fields = [u[0].numpy(), v[0].numpy()]
    ang = np.deg2rad(PAPER_ANGLES_DEG)

    def step():
        fields[:] = ref.round_trip(*fields, ang, 0.1, params, *tol)
    return step


def _batch_state(batch: int, params: CavityParams, dtype, device, warm: int = 10):
    """A realistic batch: paper start, alpha1 spread over [-40, -10] deg, a few round trips in."""
    u, v = sech_fields(batch, params, dtype=dtype, device=device)
    a1 = torch.linspace(-40.0, -10.0, batch, dtype=torch.float64)
    ang = torch.stack([a1] + [torch.full_like(a1, a) for a in PAPER_ANGLES_DEG[1:]], -1)
    ang = torch.deg2rad(ang).to(device)
    K = torch.full((batch,), 0.1, dtype=torch.float64, device=device)
    for _ in range(warm):
        u, v = round_trip(u, v, ang, K, params)
    return u, v, ang, K


def torch_stepper(batch: int, params: CavityParams, dtype, device, compile: bool):
    """A realistic batch (``_batch_state``): a function doing one batched round trip per call."""
    u, v, ang, K = _batch_state(batch, params, dtype, device)
    fields = [u, v]

    def step():
        fields[:] = round_trip(*fields, ang, K, params, compile=compile)
        if fields[0].is_cuda:
            torch.cuda.synchronize()
    return step


def run_for(step, seconds: float, min_calls: int) -> tuple[int, float]:
    """Call ``step`` until ``seconds`` have passed and at least ``min_calls`` times: (calls, seconds)."""
    calls, t0 = 0, time.perf_counter()
    while calls < min_calls or time.perf_counter() - t0 < seconds:
        step()
        calls += 1
    return calls, time.perf_counter() - t0


def time_scipy(params: CavityParams, round_trips: int, tol=PAPER_TOL) -> float:
    """Seconds per round trip of the reference, from the paper's sech start (transient + settling)."""
    calls, elapsed = run_for(scipy_stepper(params, tol), 0.0, round_trips)
    return elapsed / calls


def time_torch(batch: int, params: CavityParams, dtype, device, compile: bool, min_seconds: float):
    """(seconds per batched round trip, first-call seconds incl. compilation)."""
    step = torch_stepper(batch, params, dtype, device, compile)
    t0 = time.perf_counter()
    step()
    first = time.perf_counter() - t0
    step()
    calls, elapsed = run_for(step, min_seconds, 3)
    return elapsed / calls, first


def time_fft_bound(batch: int, params: CavityParams, dtype, device) -> float:
    """Seconds per round trip spent in FFTs alone: (ifft + fft) of (B, 2, n) per evaluation."""
    x = torch.randn(batch, 2, params.n, dtype=dtype, device=device)
    for _ in range(3):
        torch.fft.fft(torch.fft.ifft(x))
    reps = max(5, 20000 // batch)
    t0 = time.perf_counter()
    for _ in range(reps):
        torch.fft.fft(torch.fft.ifft(x))
    if x.is_cuda:
        torch.cuda.synchronize()
    pair = (time.perf_counter() - t0) / reps
    return pair * fft_pairs_per_round_trip(params)


def _process_worker(kind: str, batch: int, params: CavityParams, device: str, compile: bool, seconds: float,
                    barrier, results) -> None:
    """One benchmark process (spawned): set up, wait for the others, then step for ``seconds``.

    Puts ("ok", (cavity round trips, elapsed seconds)) on ``results``, or ("error", message)."""
    try:
        torch.set_num_threads(1)  # N processes on N cores: one thread each does not oversubscribe
        if kind == "torch":
            step = torch_stepper(batch, params, torch.complex64, device, compile)
            for _ in range(2):  # compile (or load Inductor's cache) and warm up before the clock starts
                step()
        else:
            step, batch = scipy_stepper(params), 1
        barrier.wait(timeout=900)
        calls, elapsed = run_for(step, seconds, 1)
        results.put(("ok", (calls * batch, elapsed)))
    except BaseException as err:  # noqa: BLE001 - reported by the parent, which raises
        barrier.abort()
        results.put(("error", f"{type(err).__name__}: {err}"))


def time_processes(kind: str, processes: int, batch: int, params: CavityParams, device: str, compile: bool,
                   seconds: float) -> float:
    """Cavity round trips per second of ``processes`` simultaneous worker processes, summed.

    ``kind`` is "torch" (a batch of ``batch`` cavities each, one thread) or "scipy" (the
    reference, one cavity each). Workers are spawned (no fork of a process that holds
    torch threads) and start timing together on a barrier."""
    outcomes = spawn_on_barrier(_process_worker, [(kind, batch, params, device, compile, seconds)] * processes,
                                1800, f"{kind} benchmark")
    return sum(count / elapsed for count, elapsed in outcomes)


def machine_line() -> str:
    from laserrl.model import cpu_name

    cpu = cpu_name()
    return (f"{cpu}, {os.cpu_count()} cores, torch {torch.__version__} ({torch.get_num_threads()} threads), "
            f"Python {platform.python_version()}, {platform.system()}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="laserrl-bench", description=__doc__.split("\n")[0])
    parser.add_argument("--batch-sizes", type=int, nargs="+", default=[1, 64, 256, 1024])
    parser.add_argument("--scipy-round-trips", type=int, default=40)
    parser.add_argument("--min-seconds", type=float, default=3.0, help="time each batch size at least this long")
    parser.add_argument("--no-compile", action="store_true", help="time the eager solver instead of the compiled one")
    parser.add_argument("--threads", type=int, default=None, help="torch threads (default: all cores)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--skip-accuracy", action="store_true")
    parser.add_argument("--processes", type=int, default=1,
                        help="also time N simultaneous one-thread processes (torch and scipy), summed")
    parser.add_argument("--process-batch", type=int, default=256, help="batch size of each torch process")
    parser.add_argument("--compare-coarse-steps", type=int, default=None, metavar="N",
                        help="also time (and sweep) the split-step solver with an N-step coarse pass "
                             "(CavityParams(z_steps_coarse=N); 8: the classic (8, 16) pair), in alternation "
                             "with the default, and print the speed ratio")
    parser.add_argument("--compare-repeats", type=int, default=3,
                        help="alternating timings of default and comparison per batch size (median)")
    parser.add_argument("--k-sweep", action="store_true",
                        help="print the worst one-round-trip error over K, angles and sech / noise starts "
                             "instead of timing")
    parser.add_argument("--sweep-round-trips", type=int, default=30, help="round trips per start of --k-sweep")
    parser.add_argument("--train-loop", action="store_true",
                        help="instead of the solver timings: frames per second of the whole training loop "
                             "(laserrl.bench_train), with the split between simulation and learning, for one "
                             "process with all threads, one with one thread and --processes at once")
    parser.add_argument("--train-frames", type=int, default=3072, help="frames of each --train-loop run")
    parser.add_argument("--train-warmup-frames", type=int, default=1024,
                        help="frames of each --train-loop run not counted (compilation, random frames)")
    parser.add_argument("--train-override", action="append", default=[], metavar="KEY=VALUE",
                        help="a laserrl-train override for the --train-loop runs (repeatable), e.g. stage=siso")
    args = parser.parse_args(argv)
    for b in args.batch_sizes:
        if b < 1:
            parser.error(f"--batch-sizes must be positive, got {b}")
    if args.processes < 1:
        parser.error(f"--processes must be positive, got {args.processes}")
    if args.process_batch < 1:
        parser.error(f"--process-batch must be positive, got {args.process_batch}")
    if args.compare_repeats < 1 or args.sweep_round_trips < 1:
        parser.error("--compare-repeats and --sweep-round-trips must be positive")
    if args.train_loop:
        if args.train_frames <= args.train_warmup_frames or args.train_warmup_frames < 0:
            parser.error("--train-frames must exceed --train-warmup-frames (>= 0)")
        from laserrl.bench_train import print_train_loop

        print(f"machine: {machine_line()}")
        print_train_loop(args.train_frames, args.processes, tuple(args.train_override), args.train_warmup_frames)
        return 0
    torch.set_num_threads(args.threads or os.cpu_count() or 1)
    params = CavityParams()
    compare = None
    if args.compare_coarse_steps is not None:
        try:
            compare = params.replace(z_steps_coarse=args.compare_coarse_steps)
        except ValueError as err:
            parser.error(str(err))
    dtype = torch.complex64
    compile = not args.no_compile
    if args.k_sweep:
        print(f"machine: {machine_line()}")
        settings = {f"default, split passes {params.split_passes}": params}
        if compare is not None:
            settings[f"split passes {compare.split_passes}"] = compare
        print_k_sweep(sweep_references(round_trips=args.sweep_round_trips), settings)
        return 0
    print(f"machine: {machine_line()}")
    print(f"reference: scipy.integrate.ode DOP853 per round trip, rtol {_sci(PAPER_TOL[0])}, atol {_sci(PAPER_TOL[1])} "
          f"(the paper's code); also at rtol {_sci(LOOSE_TOL[0])}, atol {_sci(LOOSE_TOL[1])}")
    print(f"settings: complex64, integrator {params.integrator}, z_steps={params.z_steps} "
          f"(split passes {params.split_passes}: {fft_pairs_per_round_trip(params)} FFT pairs per round trip), "
          f"{'compiled' if compile else 'eager'}, device {args.device}")

    data = None if args.skip_accuracy else _reference_data()
    acc_torch = acc_scipy = acc_loose = float("nan")
    if data is not None:
        acc_torch = torch_accuracy(data, params)
        acc_scipy = scipy_accuracy(data, params)
        acc_loose = scipy_accuracy(data, params, LOOSE_TOL)

    # The reference is timed before, between and after the torch timings, and the median is
    # used: the host's speed drifts over a run, and one short timing of it moves every ratio.
    ref_times = [time_scipy(params, args.scipy_round_trips)]
    loose_rate = 1.0 / time_scipy(params, args.scipy_round_trips, LOOSE_TOL)
    measured = []  # (name, batch, rate, fft-bound rate, accuracy, first call)
    speed_ratios = []  # (batch, default rate / comparison rate, each timing's ratio)
    acc_compare = float("nan")
    if compare is not None and data is not None:
        acc_compare = torch_accuracy(data, compare)
    for batch in args.batch_sizes:
        if compare is None:
            per_rt, first = time_torch(batch, params, dtype, args.device, compile, args.min_seconds)
            rate = batch / per_rt
        else:  # alternate, so that a drift of the host's speed moves both alike
            rates, old_rates, firsts = [], [], []
            for _ in range(args.compare_repeats):
                per_rt, first = time_torch(batch, params, dtype, args.device, compile, args.min_seconds)
                rates.append(batch / per_rt)
                firsts.append(first)
                per_rt, _ = time_torch(batch, compare, dtype, args.device, compile, args.min_seconds)
                old_rates.append(batch / per_rt)
            rate, old_rate, first = statistics.median(rates), statistics.median(old_rates), firsts[0]
            pair_ratios = [r / o for r, o in zip(rates, old_rates)]
            speed_ratios.append((batch, statistics.median(pair_ratios), pair_ratios))
        fft_rt = time_fft_bound(batch, params, dtype, args.device)
        measured.append((f"torch batch {batch}", batch, rate, batch / fft_rt, acc_torch, first))
        if compare is not None:
            measured.append((f"torch batch {batch}, split passes {compare.split_passes}", batch, old_rate,
                             batch / time_fft_bound(batch, compare, dtype, args.device), acc_compare, float("nan")))
        print(f"  measured batch {batch}: {rate:,.0f} round trips/s", file=sys.stderr, flush=True)
    ref_times.append(time_scipy(params, args.scipy_round_trips))
    machine_ref = float("nan")
    if args.processes > 1:
        n, batch = args.processes, args.process_batch
        machine_ref = time_processes("scipy", n, 1, params, args.device, compile, args.min_seconds)
        machine_rate = time_processes("torch", n, batch, params, args.device, compile, args.min_seconds)
        print(f"  measured {n} processes: torch {machine_rate:,.0f}, scipy {machine_ref:,.0f} round trips/s",
              file=sys.stderr, flush=True)
    ref_times.append(time_scipy(params, args.scipy_round_trips))
    t_ref = statistics.median(ref_times)
    ref_rate = 1.0 / t_ref
    rows = [(f"{SCIPY_PAPER}, 1 cavity", 1, ref_rate, 1.0, float("nan"), acc_scipy, float("nan")),
            (f"{SCIPY_LOOSE}, 1 cavity", 1, loose_rate, loose_rate / ref_rate, float("nan"), acc_loose, float("nan"))]
    rows += [(name, b, rate, rate / ref_rate, bound, acc, first) for name, b, rate, bound, acc, first in measured]
    per_batch = rows[2:]
    if args.processes > 1:
        rows.append((f"{SCIPY_PAPER}, {n} processes x 1 cavity", 1, machine_ref, machine_ref / ref_rate,
                     float("nan"), acc_scipy, float("nan")))
        rows.append((f"torch {n} processes x batch {batch} (1 thread each)", batch, machine_rate,
                     machine_rate / ref_rate, float("nan"), acc_torch, float("nan")))

    print(f"reference timed {len(ref_times)} times ({args.scipy_round_trips} round trips each, before, between and "
          f"after the torch timings): {', '.join(f'{t * 1e3:.1f}' for t in ref_times)} ms per round trip; "
          f"the ratios use the median")
    print()
    print("| solver | batch | cavity round trips / s | x scipy | FFT-bound round trips / s | max rel. error vs reference | first call (s) |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for name, batch, rate, ratio, bound, acc, first in rows:
        fmt = lambda x, f: "-" if (isinstance(x, float) and math.isnan(x)) else format(x, f)  # noqa: E731
        print(f"| {name} | {batch} | {rate:,.0f} | {fmt(ratio, ',.0f' if ratio >= 10 else '.2g')} | {fmt(bound, ',.0f')} | {fmt(acc, '.1e')} | {fmt(first, '.1f')} |")
    if speed_ratios:
        print()
        for batch, ratio, each in speed_ratios:
            print(f"speed of split passes {params.split_passes} relative to {compare.split_passes} at batch {batch}: "
                  f"{ratio:.3f} (median of {len(each)} alternating timings: {', '.join(f'{r:.3f}' for r in each)})")
    per_batch = [r for r in per_batch if "split passes" not in r[0]]
    best = max(per_batch, key=lambda r: r[2])
    print()
    print(f"best: {best[2]:,.0f} cavity round trips/s at batch {best[1]} = {best[3]:,.0f}x the scipy reference "
          f"({t_ref * 1e3:.1f} ms per round trip at the paper's tolerance; {best[2] / loose_rate:,.0f}x scipy at "
          f"rtol {_sci(LOOSE_TOL[0])}, {1e3 / loose_rate:.1f} ms); FFTs alone would allow {best[4]:,.0f}/s")
    if args.processes > 1:
        print(f"whole machine: {machine_rate:,.0f} cavity round trips/s with {args.processes} processes = "
              f"{machine_rate / ref_rate:,.0f}x the one-process scipy reference, {machine_rate / machine_ref:,.0f}x "
              f"scipy on {args.processes} processes")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
