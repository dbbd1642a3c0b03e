"""Drift control's solver against scipy's: the time of the solve and the placement accuracy.

    python scripts/bench_drift_solver.py                 # survey and forward+backward flights, 640x360
    python scripts/bench_drift_solver.py --seeds 1 2 --survey-frames 900 --revisit-frames 300

Flights (cached under --workdir): ``mosaic simulate -p survey`` over the NEON orthophoto of
../shared/data/aerial_stills (lawnmower lines that revisit their ground) and a 'fast' flight
flown forward then backward (as ``bench_stitch.py revisits``, smaller), all with the
simulator's exact homographies.

Each flight is stitched (``orb``, drift control on) once per solver: ``lm`` is the one in
``mosaic_cli/stitch/registration.py`` (Levenberg-Marquardt, exact sparse steps); ``scipy`` is
``scipy.optimize.least_squares`` (method "trf", the same analytic sparse Jacobian, the same
weighted soft-L1 loss, ``x_scale="jac"``, LSMR steps), as drift control used it before commit
45b6c42; ``scipy-tight`` is the same with LSMR run to 1e-10 and a budget of 2000 evaluations.
Reported per flight and solver: the seconds in the solver (all refinements of the run), the
robust cost each solver reaches on the identical problems (the first run's refinements
replayed), and the median and largest corner error of keyframes at least 60 frames apart
against the exact homographies (as ``bench_stitch.py``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

from mosaic_cli.estimators import make_estimator
from mosaic_cli.geometry import corner_error
from mosaic_cli.simulate import load_ground_truth, load_map, plan_flight, write_flight
from mosaic_cli.stitch import RegistrationOptions, StitchOptions, registration, stitch
from mosaic_cli.stitch.registration import RegistrationReport, refine_placements

ROOT = Path(__file__).resolve().parents[1]
ORTHOPHOTO = ROOT.parent / "shared/data/aerial_stills/deepforest_neon_orthophoto/2019_YELL_2_528000_4978000_image_crop2.png"
SIZE = (640, 360)
GAP = 60


def scipy_solve(problem, x0: np.ndarray, options: RegistrationOptions, tight: bool = False) -> np.ndarray:
    """Drift control's solve by ``scipy.optimize.least_squares`` (trf, sparse Jacobian)."""
    extra = {"tr_options": {"atol": 1e-10, "btol": 1e-10}, "max_nfev": 2000} if tight else {"max_nfev": options.max_steps}
    result = least_squares(
        problem.residuals,
        x0,
        jac=problem.jacobian,
        method="trf",
        loss=lambda z: problem.loss(z, options.loss_scale),
        x_scale="jac",
        tr_solver="lsmr",
        xtol=1e-10,
        ftol=options.tolerance,
        **extra,
    )
    return result.x


SOLVERS = {
    "lm": registration._solve,
    "scipy": scipy_solve,
    "scipy-tight": lambda p, x, o: scipy_solve(p, x, o, tight=True),
}


# -- flights ---------------------------------------------------------------------------------


def survey(workdir: Path, frames: int, seed: int) -> tuple[Path, np.ndarray]:
    path = workdir / f"survey_{SIZE[0]}x{SIZE[1]}_{frames}_s{seed}.mp4"
    if not path.exists():
        subprocess.run(
            [sys.executable, "-m", "mosaic_cli", "simulate", str(ORTHOPHOTO), "-p", "survey", "-n", str(frames),
             "--size", f"{SIZE[0]}x{SIZE[1]}", "--seed", str(seed), "-o", str(path), "-q"],
            check=True,
        )
    return path, load_ground_truth(path.with_suffix(".gt.json")).map_to_frame


def forward_backward(workdir: Path, frames: int, seed: int) -> tuple[Path, np.ndarray]:
    path = workdir / f"fb_{SIZE[0]}x{SIZE[1]}_{frames}_s{seed}.mp4"
    if not path.exists():
        ground = load_map(ORTHOPHOTO, seed=seed)
        plan = plan_flight((ground.shape[1], ground.shape[0]), "fast", frames, SIZE, seed)
        plan = dataclasses.replace(
            plan,
            map_to_frame=np.concatenate([plan.map_to_frame, plan.map_to_frame[::-1]]),
            smooth_map_to_frame=np.concatenate([plan.smooth_map_to_frame, plan.smooth_map_to_frame[::-1]]),
        )
        write_flight(path, ground, plan, map_name=ORTHOPHOTO.name, preset="veryfast", show_progress=False)
    return path, load_ground_truth(path.with_suffix(".gt.json")).map_to_frame


def mapping(workdir: Path, seed: int) -> tuple[Path, np.ndarray]:
    """``bench_georef.py``'s mapping flight (2507 frames of 640x360 along four 410 m lines over
    a procedural map, about 118 keyframes), stitched here without its telemetry."""
    sys.path.insert(0, str(ROOT / "scripts"))
    from bench_georef import mapping_flight

    path = mapping_flight(workdir, seed)
    return path, load_ground_truth(path.with_suffix(".gt.json")).map_to_frame


def placement_errors(transforms, truth) -> np.ndarray:
    return np.array([
        corner_error(np.linalg.inv(H_j) @ H_i, truth[j] @ np.linalg.inv(truth[i]), SIZE)
        for i, H_i in transforms
        for j, H_j in transforms
        if j - i >= GAP
    ])


# -- runs ------------------------------------------------------------------------------------


def run(video: Path, truth: np.ndarray, solver, workdir: Path, captured: list | None = None) -> dict:
    """One stitch with ``solver`` in drift control: seconds in the solver, corner errors."""
    seconds = [0.0]
    real_refine = registration.refine_placements

    def timed(problem, x0, options):
        start = time.perf_counter()
        x = solver(problem, x0, options)
        seconds[0] += time.perf_counter() - start
        return x

    def capture(initial, report, reference, size, options):
        if captured is not None:
            captured.append(([P.copy() for P in initial], list(report.links), reference, size, options))
        return real_refine(initial, report, reference, size, options)

    registration._solve, registration.refine_placements = timed, capture
    try:
        result = stitch(video, workdir / f"{video.stem}.png", make_estimator("orb"), StitchOptions(), show_progress=False)
    finally:
        registration._solve, registration.refine_placements = SOLVERS["lm"], real_refine
    errors = placement_errors(result.transforms, truth)
    return {"solve_s": seconds[0], "median": float(np.median(errors)), "max": float(errors.max()),
            "keyframes": len(result.transforms), "loops": result.registration.loops}


def replay(captured: list, solver) -> tuple[float, float]:
    """The captured refinements solved again with ``solver``: seconds and the final robust cost."""
    seconds, cost = 0.0, 0.0
    for initial, links, reference, size, options in captured:
        report = RegistrationReport(links=[dataclasses.replace(l) for l in links], residual_before=1.0)
        registration._solve = solver
        try:
            start = time.perf_counter()
            placements = refine_placements(initial, report, reference, size, options)
            seconds += time.perf_counter() - start
        finally:
            registration._solve = SOLVERS["lm"]
        # The cost of the result on the problem's final links, from the placements themselves.
        problem = registration._Problem(placements, report.links, reference, size)
        cost += problem.cost(problem.residuals(np.zeros(problem.n_params)), options.loss_scale)
    return seconds, cost


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, nargs="*", default=[1, 2], help="survey and forward+backward flights of these seeds")
    parser.add_argument("--survey-frames", type=int, default=900)
    parser.add_argument("--revisit-frames", type=int, default=300)
    parser.add_argument("--mapping", type=int, nargs="*", default=[], help="also bench_georef.py's mapping flights of these seeds")
    parser.add_argument("--solvers", nargs="+", default=list(SOLVERS), choices=list(SOLVERS))
    parser.add_argument("--no-replay", dest="replay", action="store_false", help="skip solving the first run's problems again with each solver")
    parser.add_argument("--workdir", type=Path, default=ROOT / ".dev" / "bench_drift_solver")
    parser.add_argument("--json", type=Path, help="write the rows here too")
    args = parser.parse_args()
    args.workdir.mkdir(parents=True, exist_ok=True)
    rows = []
    flights = [f(args.workdir, n, seed) for seed in args.seeds for f, n in ((survey, args.survey_frames), (forward_backward, args.revisit_frames))]
    flights += [mapping(args.workdir, seed) for seed in args.mapping]
    for video, truth in flights:
        captured: list = []
        for name in args.solvers:
            row = {"flight": video.name, "solver": name}
            row.update(run(video, truth, SOLVERS[name], args.workdir, captured if not captured else None))
            rows.append(row)
            print(
                f"{row['flight']:28s} {name:12s} {row['keyframes']:3d} keyframes {row['loops']:3d} loops; solve {row['solve_s']:6.2f} s; "
                f"corner error >= {GAP} apart median {row['median']:.3f} max {row['max']:.3f} px",
                flush=True,
            )
        for name in args.solvers if args.replay else ():
            seconds, cost = replay(captured, SOLVERS[name])
            print(f"{video.name:28s} {name:12s} the same {len(captured)} problems: {seconds:6.2f} s, robust cost {cost:.6g}", flush=True)
            row = next(r for r in rows if r["flight"] == video.name and r["solver"] == name)
            row.update({"replay_s": seconds, "replay_cost": cost, "refinements": len(captured)})
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
