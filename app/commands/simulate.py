"""``lightflow simulate``: render a recording (or a calibration session) of a built-in scene."""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from pathlib import Path

from lightflow.app.core.errors import ConfigError
from lightflow.app.core.rig import EXAMPLE_RIGS, Rig, resolve_rig


def _scene_lines() -> str:
    from lightflow.drivers.sim.scenes import SCENES

    width = max(len(n) for n in SCENES)
    return "\n".join(
        f"  {s.name:<{width}}  {s.exposure_s * 1e3:>4g} ms  {s.description}"
        f"{' (planar)' if s.planar else ''}"
        for s in SCENES.values()
    )


def _description() -> str:
    return f"""\
Render a recording folder (recording.json + frames/*.png, see formats.md) of a
built-in moving scene with the synthetic camera, physically simulated: motion
blur of the projected lines, lens blur, sensor noise.  The ground truth of every
frame is written beside it as REC/ground_truth/<frame>.npz (depth at
mid-exposure, object ids, which projectors light each pixel) with
REC/ground_truth/scene.json; `lightflow eval REC` scores the pipeline on it.

Scenes (name, nominal exposure, description):
{_scene_lines()}

Rigs: a rig file, or an example rig: {", ".join(EXAMPLE_RIGS)}.

With --calibration, renders a calibration session instead (formats.md section
4): a checkerboard in --poses poses, each projector showing the Gray-code
sequence; `lightflow calibrate CAL/ --out rig.json` then recovers the rig.
Beside the session, CAL/gamma/<projector>/NNN.png are camera frames of a white
wall while each projector shows a grey ramp (levels in CAL/gamma/ramp.json),
rendered with the projector response --gamma; calibrate measures it back.

Examples:
  lightflow simulate --scene board --frames 10 --out rec-board
  lightflow simulate --scene fan --exposure 0.004 --scale 0.5 --out rec-fan
  lightflow simulate --calibration --poses 6 --out cal
  lightflow simulate --calibration --poses 8 --gamma 1.0 --out cal-linear"""


def register(subparsers) -> None:
    from lightflow.drivers.sim.scenes import SCENES

    p = subparsers.add_parser(
        "simulate",
        help="render a synthetic recording with ground truth (or a calibration session)",
        description=_description(),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--scene", choices=list(SCENES), metavar="NAME", help="built-in scene (listed above)"
    )
    p.add_argument(
        "--rig",
        default="two-projector",
        metavar="RIG",
        help="rig file or example rig name (default: two-projector)",
    )
    p.add_argument(
        "--exposure",
        type=float,
        metavar="S",
        help="exposure in seconds (default: the scene's nominal exposure)",
    )
    p.add_argument(
        "--frames", type=int, default=10, metavar="N", help="number of frames (default: 10)"
    )
    p.add_argument(
        "--out",
        type=Path,
        required=True,
        metavar="DIR",
        help="recording folder (or calibration session folder) to create",
    )
    p.add_argument(
        "--scale",
        type=float,
        default=1.0,
        metavar="F",
        help="scale the camera resolution (e.g. 0.25 for quick tests; default: 1)",
    )
    p.add_argument(
        "--fps",
        type=float,
        default=30.0,
        metavar="F",
        help="frame rate: exposure start times are i / fps (default: 30)",
    )
    p.add_argument("--seed", type=int, default=0, metavar="N", help="noise seed (default: 0)")
    p.add_argument(
        "--bit-depth",
        type=int,
        choices=(8, 16),
        default=8,
        help="bits per channel of the PNG frames (default: 8)",
    )
    p.add_argument(
        "--calibration",
        action="store_true",
        help="render a calibration session instead of a recording",
    )
    p.add_argument(
        "--poses",
        type=int,
        default=6,
        metavar="N",
        help="board poses of a calibration session (default: 6)",
    )
    p.add_argument(
        "--gamma",
        type=float,
        default=2.2,
        metavar="G",
        help="projector response of a calibration session: grey v in [0, 1] emits v**G "
        "(default: 2.2)",
    )
    p.add_argument(
        "--camera-gamma",
        type=float,
        default=1.0,
        metavar="G",
        help="camera response: DN = 255 (signal / 255) ** (1 / G) (default: 1, linear)",
    )
    p.add_argument(
        "--projector-gamma",
        type=float,
        default=1.0,
        metavar="G",
        help="projector response to the patterns' levels: level v emits (v / 255) ** G "
        "(default: 1; the rig format's 0/255 lines are unchanged by it)",
    )
    p.add_argument(
        "--projector-black",
        type=float,
        default=0.0,
        metavar="F",
        help="light a projector leaks for level 0, as a fraction of its full light "
        "(a contrast of 1:500 is 0.002) (default: 0)",
    )
    p.add_argument(
        "--lens-psf",
        choices=("gauss", "disk"),
        default="gauss",
        help="camera lens blur: gauss, or disk (defocus disc plus halo, which the "
        "reconstruction does not model) (default: gauss)",
    )
    p.add_argument(
        "--lens-blur",
        type=float,
        default=None,
        metavar="PX",
        help="lens blur in camera pixels: Gaussian sigma or disc radius (default: 0.6)",
    )
    p.add_argument(
        "--truth-flows",
        action="store_true",
        help="also write each frame's true line sweeps, line intervals (camera px) and flows "
        "(projector px) per pattern as ground_truth/<frame>_flows.npz, for `lightflow eval "
        "--stages`",
    )
    p.set_defaults(func=run)


def _scaled(rig: Rig, scale: float) -> Rig:
    if not (math.isfinite(scale) and 0 < scale <= 4):
        raise ConfigError(f"--scale: expected a factor in (0, 4], got {scale:g}")
    if scale == 1:
        return rig
    small = rig.scaled(scale)
    if small.camera.width < 16 or small.camera.height < 16:
        raise ConfigError(
            f"--scale {scale:g}: camera of {small.camera.width}x"
            f"{small.camera.height} px is too small"
        )
    return small


def _progress(stage: str, i: int, n: int) -> None:
    end = "\n" if i == n else ""
    print(f"\r{stage}: {i}/{n}", end=end, file=sys.stderr, flush=True)


def run(args: argparse.Namespace) -> int:
    rig = _scaled(resolve_rig(args.rig), args.scale)
    if args.calibration:
        return _run_calibration(args, rig)
    if args.scene is None:
        raise ConfigError("simulate: give --scene NAME (or --calibration); see --help for scenes")
    return simulate_recording(
        rig, args.scene, args.out, frames=args.frames, fps=args.fps, exposure_s=args.exposure,
        seed=args.seed, bit_depth=args.bit_depth, progress=_progress,
        camera_gamma=args.camera_gamma, lens_psf=args.lens_psf, lens_blur_px=args.lens_blur,
        projector_gamma=args.projector_gamma, projector_black=args.projector_black,
        truth_flows=args.truth_flows,
    )  # fmt: skip


def simulate_recording(
    rig: Rig,
    scene: str,
    out: Path,
    *,
    frames: int = 10,
    fps: float = 30.0,
    exposure_s: float | None = None,
    seed: int = 0,
    bit_depth: int = 8,
    progress=None,
    camera_gamma: float = 1.0,
    lens_psf: str = "gauss",
    lens_blur_px: float | None = None,
    projector_gamma: float = 1.0,
    projector_black: float = 0.0,
    truth_flows: bool = False,
) -> int:
    """Render ``frames`` frames of ``scene`` into the recording folder ``out``, with truth.

    ``camera_gamma``, ``lens_psf``, ``lens_blur_px``, ``projector_gamma`` and
    ``projector_black`` select physics the reconstruction does not model
    (see :class:`~lightflow.drivers.sim.synthetic.SensorModel`).
    ``truth_flows`` also writes each frame's true sweeps, line intervals and flows
    as ``ground_truth/<frame>_flows.npz`` (:class:`lightflow.app.stages.TrueFlows`).
    Returns the exit status (0).
    """
    from lightflow.app.evaluation import SCENE_FORMAT, SCENE_JSON, TRUTH_DIR
    from lightflow.app.recording import RecordingWriter
    from lightflow.drivers.sim.scenes import get_scene
    from lightflow.drivers.sim.synthetic import SensorModel, SyntheticCamera

    info = get_scene(scene)
    exposure = info.exposure_s if exposure_s is None else float(exposure_s)
    if frames < 1:
        raise ConfigError(f"--frames: expected at least 1, got {frames}")
    if not (math.isfinite(fps) and fps > 0):
        raise ConfigError(f"--fps: expected a positive frame rate, got {fps:g}")
    if not 1e-5 <= exposure <= 1.0:
        raise ConfigError(f"--exposure: expected 1e-05 .. 1 s, got {exposure:g}")
    if exposure > 1.0 / fps * (1 + 1e-9):
        raise ConfigError(
            f"--exposure: {exposure:g} s is longer than the frame period 1/fps = "
            f"{1.0 / fps:.4g} s; lower --fps"
        )
    if not (math.isfinite(camera_gamma) and 0.2 <= camera_gamma <= 5):
        raise ConfigError(f"--camera-gamma: expected 0.2 .. 5, got {camera_gamma:g}")
    if not (math.isfinite(projector_gamma) and 0.2 <= projector_gamma <= 5):
        raise ConfigError(f"--projector-gamma: expected 0.2 .. 5, got {projector_gamma:g}")
    if not (math.isfinite(projector_black) and 0 <= projector_black <= 0.1):
        raise ConfigError(
            f"--projector-black: expected 0 .. 0.1 (a contrast of at least 1:10), "
            f"got {projector_black:g}"
        )
    if lens_blur_px is not None and not (math.isfinite(lens_blur_px) and 0 <= lens_blur_px <= 10):
        raise ConfigError(f"--lens-blur: expected 0 .. 10 px, got {lens_blur_px:g}")
    out = Path(out)
    if (out / "recording.json").exists():
        raise ConfigError(f"{out}: already holds a recording, choose a new folder")
    tdir = out / TRUTH_DIR
    tdir.mkdir(parents=True, exist_ok=True)
    scene_doc = {
        "format": SCENE_FORMAT,
        "scene": info.name,
        "description": info.description,
        "exposure_s": exposure,
        "fps": fps,
        "seed": seed,
        "planar": info.planar,
        "rig_digest": rig.geometry_digest(),
        "sensor": {"camera_gamma": camera_gamma, "lens_psf": lens_psf,
                   "lens_blur_px": lens_blur_px, "projector_gamma": projector_gamma,
                   "projector_black": projector_black},
    }
    (tdir / SCENE_JSON).write_text(json.dumps(scene_doc, indent=1) + "\n")

    flows_renderer = None
    if truth_flows:
        from lightflow.drivers.sim.synthetic import SceneRenderer

        flows_renderer = SceneRenderer(rig, info)

    def save_truth(root: Path, frame) -> None:
        # runs on the writer thread, after the frame PNG and before recording.json lists it
        frame.extras["truth"].save(root / TRUTH_DIR / f"{frame.stem}.npz")
        if flows_renderer is not None:
            from lightflow.app.stages import FLOWS_SUFFIX, true_flows

            flows = true_flows(flows_renderer, frame.timestamp, exposure)
            flows.save(root / TRUTH_DIR / f"{frame.stem}{FLOWS_SUFFIX}")

    sensor = SensorModel(bit_depth=bit_depth, camera_gamma=camera_gamma, lens_psf=lens_psf,
                         projector_gamma=projector_gamma, projector_black=projector_black)
    if lens_blur_px is not None:
        sensor = dataclasses.replace(sensor, lens_blur_px=float(lens_blur_px))
    camera = SyntheticCamera(rig, scene, frames=frames, fps=fps, exposure_s=exposure,
                             seed=seed, sensor=sensor)  # fmt: skip
    # rendering is far slower than writing, so the writer never has to drop a frame
    writer = RecordingWriter(out, rig, exposure, put_timeout_s=600.0, extra=save_truth)
    try:
        with camera:
            for i, frame in enumerate(camera.frames()):
                if not writer.write(frame):
                    raise ConfigError(f"{out}: frame {frame.stem} could not be written in time")
                if progress:
                    progress("simulate", i + 1, frames)
    finally:
        writer.close()
    cam = rig.camera
    print(f"{out}: {writer.written} frames of {info.name!r}, {cam.width}x{cam.height}, "
          f"exposure {exposure * 1e3:g} ms, {bit_depth}-bit; ground truth in {tdir}")  # fmt: skip
    return 0


def _run_calibration(args: argparse.Namespace, rig: Rig) -> int:
    from lightflow.calibration.simulate import SimParams, simulate_gamma_ramps, simulate_session

    if args.poses < 1:
        raise ConfigError(f"--poses: expected at least 1, got {args.poses}")
    if not (math.isfinite(args.gamma) and 0.2 <= args.gamma <= 5):
        raise ConfigError(f"--gamma: expected 0.2 .. 5, got {args.gamma:g}")
    params = SimParams(gamma=args.gamma)
    if (args.out / "session.json").exists():
        raise ConfigError(f"{args.out}: already holds a calibration session, choose a new folder")
    try:
        session = simulate_session(
            rig,
            args.poses,
            args.out,
            seed=args.seed,
            params=params,
            progress=lambda i, n: _progress("simulate", i, n),
        )
    except ValueError as exc:  # no usable board pose for this rig
        raise ConfigError(f"--rig {args.rig}: {exc}") from None
    ramp = simulate_gamma_ramps(rig, args.out, seed=args.seed, params=params)
    n = len(session.poses)
    print(
        f"{args.out}: calibration session of {n} pose{'s' if n != 1 else ''}, "
        f"{len(rig.projectors)} projector(s); grey ramps (gamma {args.gamma:g}) in "
        f"{ramp.parent}; ground truth in {args.out}/ground_truth.json"
    )
    return 0
