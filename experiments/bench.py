"""``lobula bench``: frames/s of each stage and end to end, and memory, on synthetic footage.

Speed is measured here, never asserted in tests. Footage is rendered once per size into
a temporary folder (the renderer is timed apart, :func:`bench_render`), then the velocity
pipeline streams it as a user's run would: decode (read), dense flow (flow), derotation +
epipole + field pooling (fields) and the readout over the whole run (readout).
"""
from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path

import numpy as np


def _rss_mb() -> float:
    """Current resident memory of this process (MiB), from /proc."""
    try:
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2 ** 20
    except OSError:
        return float("nan")


def _peak_mb() -> float:
    import resource
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def bench_velocity(folder: Path, preset: str) -> dict:
    from lobula.velocity import estimate_velocity
    from lobula.config import VelocityConfig
    from lobula.readers import open_footage

    fo = open_footage(folder)
    cfg = VelocityConfig()
    cfg.flow.dis_preset = preset
    t0, c0 = time.perf_counter(), time.process_time()
    ds = estimate_velocity(fo, cfg, progress=False)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    import json
    tm = json.loads(ds.attrs["timings_s"])
    n = len(fo)
    # CPU: every thread of this process (the decode, flow and fields stages overlap, and OpenCV and
    # numpy run threads of their own), so it can exceed the wall time; per frame, imports excluded.
    return dict(frames=n, wall=wall, **{k: n / v if v > 0 else float("inf") for k, v in tm.items()},
                end_to_end=n / wall, cpu_ms_per_frame=1000.0 * cpu / n)


def bench_streaming(folder: Path, preset: str) -> dict:
    """Per-frame latency of :class:`lobula.VelocityEstimator` (the causal pipeline frame by frame): the wall
    time of each ``update(frame, t, imu)`` that makes an estimate, frames decoded beforehand. Returns its
    median and 99th percentile (ms) and the frames/s of their sum."""
    from lobula.config import VelocityConfig
    from lobula.readers import open_footage
    from lobula.velocity import VelocityEstimator

    fo = open_footage(folder)
    cfg = VelocityConfig()
    cfg.flow.dis_preset = preset
    cfg.readout.filter = "causal"
    est = VelocityEstimator(fo.camera, cfg)
    imu, j, lat = fo.imu, 0, []
    for _, t, image in fo.frames():
        k = int(np.searchsorted(imu.time_s, t, side="right"))
        chunk = (imu.time_s[j:k], imu.gyro[j:k], imu.accel[j:k])
        j = k
        t0 = time.perf_counter()
        est.update(image, t, chunk)
        made = est.drain()
        if made:
            lat.append(1000.0 * (time.perf_counter() - t0))
    lat = np.array(lat)
    return dict(stream_median_ms=float(np.median(lat)), stream_p99_ms=float(np.percentile(lat, 99)),
                stream_fps=1000.0 * len(lat) / float(lat.sum()))


def bench_command(folder: Path, preset: str, repeats: int = 1) -> dict:
    """The user's view: `lobula velocity` as a separate process, start-up measured apart.

    Start-up is the wall time of the same command on a folder that does not exist (it imports
    the pipeline, then stops at its first input check); frames/s is frames over the rest of a
    full run's wall time (decode, flow, fields, readout, NetCDF output). Medians over ``repeats``.
    """
    import subprocess
    import sys

    def wall(*args) -> float:
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "experiments.cli", "velocity", *args, "--quiet"],
                       capture_output=True, check=False)
        return time.perf_counter() - t0

    with tempfile.TemporaryDirectory() as tmp:
        out = str(Path(tmp) / "run.nc")
        startup = float(np.median([wall(str(Path(tmp) / "missing"), "--out", out) for _ in range(repeats)]))
        full = float(np.median([wall(str(folder), "--dis-preset", preset, "--out", out) for _ in range(repeats)]))
    n = len(list((folder / "frames").iterdir()))
    # Under load the two walls can come out nearly equal; a frame rate from their difference would then
    # be noise, so it is reported as NaN (lengthen --frames) rather than as a huge number.
    work = full - startup
    return dict(frames=n, startup_s=startup, command_s=full,
                command_fps=n / work if work > 0.1 * full else float("nan"))


def bench_emd(folder: Path, n_ommatidia: int = 5000) -> dict:
    """Stages of the EMD front end (sampling, photoreceptors, EMDs, fields) on a footage folder."""
    from dataclasses import replace

    from lobula.velocity import field_rates
    from lobula.config import VelocityConfig
    from lobula.lattice import dphi_for_count
    from lobula.readers import open_footage

    fo = open_footage(folder)
    cfg = VelocityConfig(front_end="emd")
    cfg.emd.lattice = replace(cfg.emd.lattice, dphi_deg=dphi_for_count(fo.camera, n_ommatidia, cfg.emd.lattice))
    rates = field_rates(fo, cfg, progress=False)
    tm = dict(rates.timings)
    n_omm = tm.pop("n_ommatidia")
    tm.pop("n_saccades", None)
    wall = sum(tm.values())
    n = len(rates.t)
    stages = {k: n / v if v > 0 else float("inf") for k, v in tm.items()}
    front = sum(v for k, v in tm.items() if k != "read")
    return dict(frames=n, n_ommatidia=n_omm, dphi_deg=cfg.emd.lattice.dphi_deg, **stages,
                emd_front_end=n / front, end_to_end=n / wall)


def _sync(device) -> None:
    """Wait for the device's queued kernels, so a timer reads the work and not its launch."""
    from lobula._optional import torch

    if torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


def check_device(device: str) -> None:
    """Fail loudly (ValueError) when ``device`` is not a torch device this machine has."""
    from lobula._optional import torch_device

    torch_device(device)


def _tv_flows(scale: float, n_frames: int, seed: int = 0):
    """Exact forward flow of a 0.4 m/s run plus DIS-like noise: (camera, [(flow (2, H, W) float32, epipole)])."""
    from lobula.camera import PinholeCamera
    from stimuli.scene import SceneConfig, TrackScene
    from stimuli.trajectory import trajectory_from_function

    cam = PinholeCamera().scaled(scale)
    scene = TrackScene(cam, trajectory_from_function(lambda t: np.full_like(t, 0.4), 3.0), SceneConfig())
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n_frames):
        t0 = 0.5 + 0.2 * k
        flow = scene.flow(t0, t0 + 0.2) / 0.2 + rng.normal(0, 0.002, (2, cam.height, cam.width))
        out.append((flow.astype(np.float32), scene.epipole(t0)))
    return cam, out


def bench_tv_depth(n_frames: int = 10, gamma: float = 1e-6, device: str = "cpu", scale: float = 0.5) -> dict:
    """ms per TV depth map (cold start) on exact flow plus DIS-like noise, at ``scale`` × 640×480.

    On the CPU it uses one torch thread (the velocity pipeline's setting); on a GPU the
    flow is copied there before the clock starts and the clock waits for the kernels.
    """
    from lobula._optional import torch
    from lobula.depth import depth_tv

    cam, flows = _tv_flows(scale, n_frames)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    ms = []
    try:
        depth_tv(torch.from_numpy(flows[0][0]).to(device), cam, 0.4, flows[0][1], gamma=gamma)  # warm-up
        for flow, epipole in flows:
            f = torch.from_numpy(flow).to(device)
            _sync(device)
            tic = time.perf_counter()
            depth_tv(f, cam, 0.4, epipole, gamma=gamma)
            _sync(device)
            ms.append(1000 * (time.perf_counter() - tic))
    finally:
        torch.set_num_threads(threads)
    return dict(median_ms=float(np.median(ms)), max_ms=float(np.max(ms)), device=device,
                size=f"{cam.width}x{cam.height}")


def agreement_on_device(device: str, duration_s: float = 0.3) -> dict:
    """Largest differences between CPU and ``device`` on the torch stages (same inputs).

    circuit: LC rates of the 5,000-ommatidia eye's population (rate model, deterministic)
    to three drifting gratings, relative to the largest rate; tv_depth: one 320×240 TV
    depth map, relative to its median. Float32 rounding differs between devices, so these
    are small but not zero.
    """
    from lobula._optional import torch
    from lobula.camera import PinholeCamera
    from lobula.circuit import Circuit, CircuitConfig
    from lobula.depth import depth_tv
    from lobula.lattice import Lattice, LatticeConfig, dphi_for_count
    from lobula.population import LCNeuronConfig, LCPopulationConfig
    from stimuli.lattice_stimuli import GratingSource

    dt = 1e-3
    camera = PinholeCamera(frame_rate_hz=1.0 / dt).scaled(0.5)
    lat = Lattice(camera, LatticeConfig(dphi_deg=dphi_for_count(camera, 5000)))
    cfg = CircuitConfig(population=LCPopulationConfig(neurons=LCNeuronConfig(model="rate")), dt_s=dt)
    rates = {}
    for dev in ("cpu", device):
        src = GratingSource(lat, kind="drum", temporal_freq_hz=[1.0, 4.0, 16.0], contrast=0.5, frame_rate_hz=1.0 / dt,
                            device=dev)
        rec = Circuit(lat, cfg, device=dev).run(src, int(round(duration_s / dt)), record=("lc.rate",), seed=0,
                                                baseline=1.0)
        rates[dev] = rec["lc.rate"].detach().to("cpu", torch.float64)
    circuit = float((rates[device] - rates["cpu"]).abs().max() / rates["cpu"].abs().max())
    cam, flows = _tv_flows(0.5, 1)
    z = {dev: depth_tv(torch.from_numpy(flows[0][0]).to(dev), cam, 0.4, flows[0][1]).depth for dev in ("cpu", device)}
    zc, zd = (torch.as_tensor(z[k]).detach().to("cpu", torch.float64) for k in ("cpu", device))
    tv = float((zd - zc).abs().nanmedian() / zc.nanmedian())
    return dict(circuit_max_rel=circuit, tv_depth_median_rel=tv)


def bench_render(scale: float, frames: int = 30) -> dict:
    """Frames/s of the synthetic world's renderer at the D435i camera scaled by ``scale``: ``lobula
    scene``'s frames of its default scene (frontal panels, 2×2 rays a pixel), the frames alone (no
    depth maps, IMU or PNG writing)."""
    from stimuli.scene import SceneConfig
    from stimuli.track import TrackRunConfig, build_track

    scene, _ = build_track(TrackRunConfig(profile=None, start_s=5.0, duration_s=frames / 30.0, scale=scale,
                                          scene=SceneConfig()))
    times = np.arange(frames) / 30.0
    scene.render(0.0)  # first call: caches warm
    t0 = time.perf_counter()
    for k, t in enumerate(times):
        scene.render(float(t), k)
    wall = time.perf_counter() - t0
    return dict(size=f"{scene.camera.width}x{scene.camera.height}", render_fps=frames / wall)


def run_device_bench(device: str) -> list[dict]:
    """The torch stages on ``device`` beside the CPU: agreement, then timings (printed and returned).

    The velocity pipeline's DIS flow and field pooling run in OpenCV/NumPy on the CPU and
    have no device path; what a GPU can take is the EMD circuit (virtual electrophysiology)
    and TV depth.
    """
    from lobula._optional import torch

    from experiments.ephys import bench_tuning_sweep

    check_device(device)
    name = torch.cuda.get_device_name(device) if torch.device(device).type == "cuda" else "CPU"
    print(f"lobula bench --device {device} ({name}; torch {torch.__version__}, {os.cpu_count()} CPUs)")
    agree = agreement_on_device(device)
    print(f"agreement with the CPU: LC rates max |Δ| {agree['circuit_max_rel']:.2e} of the largest rate; "
          f"TV depth median |Δ| {agree['tv_depth_median_rel']:.2e} of the median depth")
    rows = [dict(agreement=True, **agree)]
    print("ephys tuning sweep (20 TF x 5 contrasts x 10 trials, 2 s at 1 ms, 5,000-ommatidia eye + LC population):")
    for dev, threads in (("cpu", 1), ("cpu", None), (device, None)):
        rows.append(bench_tuning_sweep(device=dev, threads=threads))
    for scale in (0.5, 1.0):
        for dev in ("cpu", device):
            tv = bench_tv_depth(device=dev, scale=scale)
            print(f"TV depth at {tv['size']} on {dev}: median {tv['median_ms']:.1f} ms/map, max {tv['max_ms']:.1f} ms")
            rows.append(tv)
    return rows


#: stages `lobula bench --skip` leaves out, and what each times
SKIPPABLE = {"render": "the synthetic world's renderer", "emd": "the EMD front end (torch)",
             "ephys": "the ephys tuning sweep (torch, ~70 s)", "tv": "TV depth (torch)"}


def run_bench(frames: int = 120, scales=(1.0, 0.5), presets=("fast", "medium"), skip=()) -> list[dict]:
    """Print a table of frames/s per stage for each image size and DIS preset; return the rows.

    skip: names of :data:`SKIPPABLE` stages not to time (the camera pipeline's stages always run).
    """
    import cv2

    from stimuli.scene import SceneConfig
    from stimuli.track import TrackRunConfig, make_track_run

    rows = []
    from lobula._optional import optional_torch, require_torch

    skip = set(skip)
    torch = optional_torch()
    if torch is None and not {"emd", "ephys", "tv"} <= skip:
        require_torch("timing the EMD front end, the ephys sweep and TV depth (or --skip emd ephys tv)")
    threads = torch.get_num_threads() if torch is not None else "-"
    print(f"lobula bench: {frames} frames per run, OpenCV threads {cv2.getNumThreads()}, "
          f"torch threads {threads}, {os.cpu_count()} CPUs, load average "
          f"{os.getloadavg()[0]:.1f}.\nStage figures are frames/s of that stage alone; end-to-end is "
          f"estimate_velocity in this process (decode included), CPU ms/frame its CPU time over all "
          f"threads; command is `lobula velocity` as its own process, frames/s after its start-up, which is "
          f"given apart; frame-by-frame is lobula.VelocityEstimator's latency per frame (median / 99th "
          f"percentile, ms), the causal filter run as frames come, decoding excluded")
    header = (f"{'size':>9} {'DIS':>7} {'read':>8} {'flow':>8} {'fields':>8} {'readout':>9} {'end-to-end':>11} "
              f"{'CPU ms/frame':>12} {'command':>8} {'start-up s':>10} {'RSS MiB':>8} {'frame-by-frame ms':>18}")
    with tempfile.TemporaryDirectory() as tmp:
        for scale in scales:
            cfg = TrackRunConfig(profile=None, start_s=5.0, duration_s=frames / 30.0, scale=scale,
                                 scene=SceneConfig(supersample=1))
            folder = make_track_run(Path(tmp) / f"s{scale}", cfg, progress=False)
            for preset in presets:
                rss0 = _rss_mb()
                r = bench_velocity(folder, preset)
                r.update(bench_command(folder, preset))
                r.update(bench_streaming(folder, preset))
                r.update(size=f"{int(640 * scale)}x{int(480 * scale)}", preset=preset, rss_mb=_rss_mb(),
                         rss_growth_mb=_rss_mb() - rss0)
                rows.append(r)
                if len(rows) == 1:
                    print(header)
                print(f"{r['size']:>9} {preset:>7} {r['read']:8.0f} {r['flow']:8.1f} {r['fields']:8.0f} "
                      f"{r['readout']:9.0f} {r['end_to_end']:11.1f} {r['cpu_ms_per_frame']:12.1f} "
                      f"{r['command_fps']:8.1f} {r['startup_s']:10.2f} {r['rss_mb']:8.0f} "
                      f"{r['stream_median_ms']:8.1f} / {r['stream_p99_ms']:<7.1f}")
            if "render" not in skip:
                rr = bench_render(scale)
                print(f"rendering the synthetic world at {rr['size']} (lobula scene's default scene, 2x2 rays a "
                      f"pixel): {rr['render_fps']:.1f} frames/s")
                rows.append(rr)
            if scale == 0.5 and "emd" not in skip:
                e = bench_emd(folder)
                print(f"EMD front end, {e['n_ommatidia']} ommatidia (Δφ {e['dphi_deg']:.2f}°) on {r['size']}: "
                      f"sampling {e['sampling']:.0f}, photoreceptor {e['photoreceptor']:.0f}, EMD {e['emd']:.0f}, "
                      f"fields {e['fields']:.0f} frames/s; front end {e['emd_front_end']:.0f} frames/s; "
                      f"with PNG decoding {e['end_to_end']:.0f} frames/s (after building the eye once)")
                rows.append(e)
    if "ephys" not in skip:
        from experiments.ephys import bench_tuning_sweep

        print("ephys tuning sweep (20 TF x 5 contrasts x 10 trials, 2 s at 1 ms, 5,000-ommatidia eye + LC "
              "population):")
        rows.append(bench_tuning_sweep())
    if "tv" not in skip:
        tv = bench_tv_depth()
        print(f"TV depth (lobula depth --method tv) at 320x240, cold start, 1 torch thread: "
              f"median {tv['median_ms']:.0f} ms/map, max {tv['max_ms']:.0f} ms")
        rows.append(tv)
    print(f"peak resident memory {_peak_mb():.0f} MiB. Memory is flat in footage length: frames are "
          f"streamed and only gap+1 frames are held; a run of N frames keeps O(N·fields) numbers.")
    return rows


def _run(args) -> int:
    if args.device != "cpu":
        check_device(args.device)
        run_device_bench(args.device)
        return 0
    from lobula.flow import FlowConfig

    gap = FlowConfig().gap
    if args.frames <= gap:
        raise ValueError(f"--frames {args.frames}: the flow pairs frames {gap} apart, so a run needs at least "
                         f"{gap + 1} frames (figures mean little under 30)")
    run_bench(frames=args.frames, scales=args.scales, presets=args.presets, skip=args.skip)
    return 0


def add_parser(subparsers):
    """Register `lobula bench` (see experiments.cli)."""
    from .parsers import COUNT, POSITIVE

    b = subparsers.add_parser("bench", help="frames/s per stage and end to end, peak memory")
    b.add_argument("--frames", type=COUNT, default=120, help="frames rendered per image size")
    b.add_argument("--scales", type=POSITIVE, nargs="+", default=[1.0, 0.5], help="image scales of the D435i camera")
    b.add_argument("--presets", nargs="+", default=["fast", "medium"], choices=["ultrafast", "fast", "medium"],
                   help="DIS presets to time")
    b.add_argument("--device", default="cpu",
                   help="cpu: the whole pipeline on this CPU. cuda (or cuda:N): only the torch stages (EMD circuit "
                        "tuning sweep, TV depth), on that GPU beside this CPU, after checking they agree; "
                        "--frames/--scales/--presets do not apply (DIS flow has no GPU path)")
    b.add_argument("--skip", nargs="+", default=[], choices=list(SKIPPABLE), metavar="STAGE",
                   help="stages not to time: " + "; ".join(f"{k}: {v}" for k, v in SKIPPABLE.items())
                        + " (default: none)")
    b.set_defaults(func=_run)
