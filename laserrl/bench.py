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
* with ``--processes N``: the whole machine, N processes of one torch thread each
  stepping their own batch at the same time (how the training collectors use a
  multi-core CPU), and for comparison N scipy reference processes at the same time.
  Their rates add up; the workers start together on a barrier and each runs for
  ``--min-seconds``.
"""
from __future__ import annotations

import argparse
import math
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

from laserrl.paths import REFERENCE_DATA
from laserrl.physics import CavityParams, round_trip, sech_fields
from laserrl.physics import reference as ref
from laserrl.physics.cavity import fft_pairs_per_round_trip

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

    Puts (cavity round trips, elapsed seconds) on ``results``, or ("error", message)."""
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
        results.put((calls * batch, elapsed))
    except BaseException as err:  # noqa: BLE001 - reported by the parent, which raises
        barrier.abort()
        results.put(("error", f"{type(err).__name__}: {err}"))


def time_processes(kind: str, processes: int, batch: int, params: CavityParams, device: str, compile: bool,
                   seconds: float) -> float:
    """Cavity round trips per second of ``processes`` simultaneous worker processes, summed.

    ``kind`` is "torch" (a batch of ``batch`` cavities each, one thread) or "scipy" (the
    reference, one cavity each). Workers are spawned (no fork of a process that holds
    torch threads) and start timing together on a barrier."""
    import multiprocessing as mp

    ctx = mp.get_context("spawn")
    barrier, results = ctx.Barrier(processes), ctx.Queue()
    workers = [ctx.Process(target=_process_worker, args=(kind, batch, params, device, compile, seconds, barrier, results))
               for _ in range(processes)]
    for w in workers:
        w.start()
    outcomes = [results.get(timeout=1800) for _ in workers]
    for w in workers:
        w.join()
    errors = [o[1] for o in outcomes if o[0] == "error"]
    if errors:
        raise RuntimeError(f"a {kind} benchmark process failed: {errors[0]}")
    return sum(count / elapsed for count, elapsed in outcomes)


def machine_line() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
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
    args = parser.parse_args(argv)
    for b in args.batch_sizes:
        if b < 1:
            parser.error(f"--batch-sizes must be positive, got {b}")
    if args.processes < 1:
        parser.error(f"--processes must be positive, got {args.processes}")
    if args.process_batch < 1:
        parser.error(f"--process-batch must be positive, got {args.process_batch}")
    torch.set_num_threads(args.threads or os.cpu_count() or 1)
    params = CavityParams()
    dtype = torch.complex64
    compile = not args.no_compile
    print(f"machine: {machine_line()}")
    print(f"reference: scipy.integrate.ode DOP853 per round trip, rtol {_sci(PAPER_TOL[0])}, atol {_sci(PAPER_TOL[1])} "
          f"(the paper's code); also at rtol {_sci(LOOSE_TOL[0])}, atol {_sci(LOOSE_TOL[1])}")
    print(f"settings: complex64, integrator {params.integrator}, z_steps={params.z_steps} "
          f"({fft_pairs_per_round_trip(params)} FFT pairs per round trip), "
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
    for batch in args.batch_sizes:
        per_rt, first = time_torch(batch, params, dtype, args.device, compile, args.min_seconds)
        fft_rt = time_fft_bound(batch, params, dtype, args.device)
        rate = batch / per_rt
        measured.append((f"torch batch {batch}", batch, rate, batch / fft_rt, acc_torch, first))
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
