"""`colmap-vc`: the command line. Parses, calls one library function, logs the summary.

Subcommands are built by tyro from dataclasses whose fields embed the library's own
options dataclasses, so defaults and help text live in one place.
Exit codes (README.md): 0 success, 1 the input or a file did not allow the run,
2 usage error, 3 a bug, 130 Ctrl-C, 143 SIGTERM; see :func:`run_command`.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import signal
import sqlite3
import sys
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import tyro

from .augment import AugmentOptions
from .mapping import MappingOptions
from .messages import (
    interrupted_message,
    os_message,
    sqlite_message,
)

if TYPE_CHECKING:
    import pycolmap

logger = logging.getLogger("colmap_vc")


@dataclass(frozen=True)
class Synth:
    """Generate a synthetic scene (images, ground truth, priors, COLMAP database)."""

    preset: tyro.conf.Positional[str]
    """Scene layout: dome, dense or pair."""
    out_dir: tyro.conf.Positional[Path]
    """Output folder (a COLMAP project)."""
    seed: int = 0
    """Seed of everything random: same seed, same files."""
    people: int = 1
    """People in the scene (1 to 3)."""
    noise: str = "realistic"
    """Noise level of the predicted priors: clean, realistic, hard, or fitted (the
    bundled estimator's fit to landmarks with the noise measured on pose2sim)."""
    extra_noise: tuple[str, ...] = ()
    """Also write priors at these levels into priors_<level>/."""
    cameras: int | None = None
    """Number of cameras (dome/dense: 8-16, drawn from the seed when unset; at most
    256 dome, 64 dense)."""
    instants: int = 1
    """Instants seen by the same static cameras, the people drawn anew at each
    (images cam00_t00.jpg, cam00_t01.jpg, ...)."""
    camera_model: str | None = None
    """COLMAP camera model (default: SIMPLE_RADIAL dome, OPENCV dense, PINHOLE pair)."""
    angle: float | None = None
    """Pair preset: angle between the two views in degrees."""
    width: int = 640
    """Image width."""
    height: int = 480
    """Image height."""
    max_features: int = 2048
    """SIFT features per image."""
    no_database: bool = False
    """Skip SIFT extraction and matching."""
    sift: bool = True
    """SIFT extraction and exhaustive matching; --no-sift writes the cameras and
    images only (VCs alone, no quadratic matching)."""
    with_ids: bool = False
    """Give the predicted priors each person's true id (default: anonymous, as a
    detector's output; the true ids are in gt/persons.json)."""
    close_pair: bool = False
    """The first two people stand 0.5-0.8 m apart and overlap in some views."""
    bystander: bool = False
    """Add a bystander 3-5 m from the group, seen by a few cameras only."""
    dress_alike: bool = False
    """The second person wears the first one's clothes."""
    overwrite: bool = False
    """Replace a non-empty OUT_DIR."""
    verbose: bool = False
    """Debug logging, COLMAP's own log included."""


@dataclass(frozen=True)
class Eval:
    """Relative pose errors and AUC@15/30/45 of a COLMAP model against ground truth."""

    pred_model: tyro.conf.Positional[Path]
    """Predicted COLMAP model folder (or folder of models 0/, 1/, ...: the largest)."""
    gt_model: tyro.conf.Positional[Path]
    """Ground-truth COLMAP model folder."""
    output: Path | None = None
    """Write the metrics as JSON here."""
    plot: Path | None = None
    """Write the cumulative error curve as a PNG here."""
    verbose: bool = False
    """Debug logging."""


@dataclass(frozen=True)
class Priors:
    """Human priors from photos, with the bundled offline estimator (MediaPipe)."""

    images: tyro.conf.Positional[Path]
    """Image folder."""
    output: Path
    """Priors folder to write (format v1, docs/priors.md)."""
    database: Path | None = None
    """COLMAP database whose cameras (intrinsics) to use; strongly recommended."""
    estimator: str = "mediapipe"
    """The estimator (only mediapipe is bundled: pip install colmap-vc[mediapipe])."""
    max_people: int = 4
    """Most people looked for per image."""
    min_person_size_px: float = 100.0
    """Skip people smaller than this (longer side of their landmarks' box), pixels."""
    detector_levels: int = 3
    """Person-detector passes: 1 whole image, 2 also squares of the shorter side,
    3 also half-size squares (people far away; ~0.5 s more per image)."""
    no_progress: bool = False
    """No progress bar."""
    overwrite: bool = False
    """Replace the priors an earlier run wrote to OUTPUT."""
    verbose: bool = False
    """Debug logging."""


@dataclass(frozen=True)
class Frames:
    """Synchronized frames of static cameras' videos, where the people moved."""

    videos: tyro.conf.Positional[tuple[Path, ...]]
    """One video per static camera."""
    output: Path
    """Image folder to write (<video stem>_f<instant>.jpg)."""
    offsets: tuple[int, ...] = ()
    """Per video, its frame index minus the first video's at the same instant."""
    instants: int = 10
    """Instants to choose (farthest apart in the people's appearance)."""
    step: int = 5
    """Candidate instants every STEP frames of the first video."""
    verbose: bool = False
    """Debug logging."""


@dataclass(frozen=True)
class Augment:
    """Add virtual correspondences from human priors to a COLMAP database."""

    database: tyro.conf.Positional[Path]
    """COLMAP database after feature extraction and matching (modified in place)."""
    priors: Path
    """Priors folder (or its priors.json), format v1 (docs/priors.md)."""
    image_path: Path | None = None
    """Image folder (accepted for symmetry with COLMAP; VCs need no pixels)."""
    options: tyro.conf.OmitArgPrefixes[AugmentOptions] = field(
        default_factory=AugmentOptions
    )
    verbose: bool = False
    """Debug logging."""


@dataclass(frozen=True)
class Map:
    """Map an augmented (or plain) COLMAP database: pycolmap mapping, keypoint BA."""

    database: tyro.conf.Positional[Path]
    """COLMAP database (augmented by `colmap-vc augment`, or plain)."""
    image_path: Path
    """Image folder."""
    output_path: Path
    """Output folder for the models (<k>/ per model; the final one is 0/)."""
    priors: Path | None = None
    """Priors (default: those `augment` recorded); the auto mapper checks its model
    against the meshes and the mesh mapper starts from them."""
    options: tyro.conf.OmitArgPrefixes[MappingOptions] = field(
        default_factory=MappingOptions
    )
    gba: bool = False
    """Refine with the generalized BA: every surface VC as a track by identity,
    weighted by its spread and its correlation with its neighbours, instead of the
    keypoint BA's fixed weight of surface VCs per image. Off by default: it is level
    on the synthetic domes and behind on pose2sim (docs/gba.md)."""
    overwrite: bool = False
    """Replace an OUTPUT_PATH that `map` wrote before (it holds a .colmap-vc-map
    marker); a folder colmap-vc did not write, or one holding the database, images or
    priors, is never removed."""
    verbose: bool = False
    """Debug logging."""


@dataclass(frozen=True)
class Strip:
    """Remove colmap-vc's VCs: the database becomes what it was before augment."""

    database: tyro.conf.Positional[Path]
    """COLMAP database."""
    force: bool = False
    """When rows colmap-vc wrote were changed after augment (e.g. re-matched), keep
    them as they are now, minus colmap-vc's VC matches, instead of refusing; only
    untouched rows get their pre-augment version back."""
    verbose: bool = False
    """Debug logging."""


@dataclass(frozen=True)
class Report:
    """A self-contained HTML report: VCs per pair colored by epipolar error, cameras,
    error curve."""

    database: tyro.conf.Positional[Path]
    """COLMAP database (augmented or plain)."""
    image_path: Path
    """Image folder."""
    output: Path = Path("report.html")
    """HTML file to write."""
    model_path: Path | None = None
    """Reconstructed COLMAP model folder."""
    gt_model_path: Path | None = None
    """Ground-truth COLMAP model folder (adds the error curve and GT-based coloring)."""
    max_pairs: int = 12
    """Image pairs shown."""
    verbose: bool = False
    """Debug logging."""


@dataclass(frozen=True)
class Demo:
    """The main job on the bundled default scene: synth, classic COLMAP, evaluation."""

    out_dir: tyro.conf.Positional[Path] = Path("out/demo")
    """Output folder."""
    overwrite: bool = False
    """Replace an existing scene in OUT_DIR."""
    verbose: bool = False
    """Debug logging."""


def _setup_logging(verbose: bool) -> None:
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(
        logging.Formatter(
            "[%(asctime)s %(name)s %(levelname)s] %(message)s", "%H:%M:%S"
        )
    )
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(logging.DEBUG if verbose else logging.INFO)
    if not verbose:
        from .colmap_log import set_min_log_level

        # COLMAP's and Ceres's glog: warnings and errors only unless --verbose.
        set_min_log_level(1)


def _load_model(path: Path) -> tuple[pycolmap.Reconstruction, Path]:
    """The model in ``path`` (or its sub-model with most images) and its folder."""
    import pycolmap

    if not path.exists():
        raise FileNotFoundError(f"model folder not found: {path}")
    if (path / "images.bin").exists() or (path / "images.txt").exists():
        return pycolmap.Reconstruction(path), path
    subs = [p for p in sorted(path.iterdir()) if (p / "images.bin").exists()]
    if not subs:
        raise FileNotFoundError(f"no COLMAP model (images.bin / images.txt) in {path}")
    models = [(pycolmap.Reconstruction(p), p) for p in subs]
    return max(models, key=lambda m: m[0].num_reg_images())


def _scale_line(model_dir: Path, ratio: float) -> str:
    """The model's size against the ground truth's: the median ratio of camera
    distances, and for a model `map` put in metres, how many of its scale's
    uncertainties that is from 1 (meaningful when the ground truth is in
    metres)."""
    import math

    from .metric_scale import read_metric_scale

    if not math.isfinite(ratio):
        return ""
    line = f"camera distances / ground truth's: {ratio:.3f}"
    scale = read_metric_scale(model_dir)
    if scale is None:
        return line + " (the model's scale is arbitrary: no metric_scale.json)"
    u = scale.uncertainty  # positive: at least the people's size error
    z = abs(math.log(ratio)) / u if ratio > 0 else math.inf
    return (
        f"{line} (model in metres, +-{100 * u:.1f}%: {z:.1f} uncertainties off, "
        "if the ground truth is in metres)"
    )


def _run_synth(cmd: Synth) -> int:
    from .synthetic import SynthOptions, generate

    summary = generate(
        cmd.preset,
        cmd.out_dir,
        SynthOptions(
            seed=cmd.seed,
            num_people=cmd.people,
            noise=cmd.noise,  # type: ignore[arg-type]
            extra_noise=tuple(cmd.extra_noise),  # type: ignore[arg-type]
            num_cameras=cmd.cameras,
            num_instants=cmd.instants,
            width=cmd.width,
            height=cmd.height,
            camera_model=cmd.camera_model,
            pair_angle_deg=cmd.angle,
            max_num_features=cmd.max_features,
            make_database=not cmd.no_database,
            sift=cmd.sift,
            overwrite=cmd.overwrite,
            with_ids=cmd.with_ids,
            close_pair=cmd.close_pair,
            bystander=cmd.bystander,
            dress_alike=cmd.dress_alike,
        ),
    )
    logger.info(
        "wrote %s (%d images, %d people)",
        summary.out_dir,
        summary.num_images,
        summary.num_people,
    )
    return 0


def _run_eval(cmd: Eval) -> int:
    from .evaluation import (
        camera_distance_ratio,
        evaluate_reconstruction,
        format_table,
        poses_by_name,
    )

    (pred, pred_dir), (gt, _) = _load_model(cmd.pred_model), _load_model(cmd.gt_model)
    names = {im.name for im in pred.images.values()}
    truth = {im.name for im in gt.images.values()}
    if not names & truth:
        raise ValueError(
            f"none of the {len(names)} images of {cmd.pred_model} is in the "
            f"ground truth {cmd.gt_model} (e.g. {min(names, default='-')!r} "
            f"against {min(truth, default='-')!r}): compare models of the same "
            "images"
        )
    if names - truth:
        logger.warning(
            "%d image(s) of the model are not in the ground truth, e.g. %s: "
            "not evaluated",
            len(names - truth),
            min(names - truth),
        )
    metrics = evaluate_reconstruction(pred, gt)
    sys.stdout.write(format_table({"prediction": metrics}) + "\n")
    ratio = camera_distance_ratio(poses_by_name(pred), poses_by_name(gt))
    scale = _scale_line(pred_dir, ratio)
    if scale:
        sys.stdout.write(scale + "\n")
    if cmd.output is not None:
        from .outputs import jsonable

        payload = jsonable({**metrics.to_dict(), "distance_ratio": ratio})
        cmd.output.write_text(json.dumps(payload, indent=1, allow_nan=False))
        logger.info("metrics written to %s", cmd.output)
    if cmd.plot is not None:
        import numpy as np

        from .report_figures import error_curve_figure

        fig = error_curve_figure(
            {"prediction": np.array([p.error_deg for p in metrics.pairs])}
        )
        fig.savefig(cmd.plot, dpi=110)
        logger.info("error curve written to %s", cmd.plot)
    return 0


def _priors_output(cmd: Priors) -> None:
    """Refuse an OUTPUT that is not a priors folder, or is in the image folder;
    an earlier run's priors are replaced only with --overwrite (priors.json is
    written last: a failed run leaves them as they were)."""
    out = cmd.output
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"--output {out} is a file, not a folder")
    images = cmd.images.resolve()
    if out.resolve() == images or images in out.resolve().parents:
        raise FileExistsError(
            f"--output {out} is inside the image folder {cmd.images}: the priors "
            "would mix with the images; choose another folder"
        )
    if not out.is_dir() or not any(out.iterdir()):
        return
    if not (out / "priors.json").is_file():
        raise FileExistsError(
            f"--output {out} is not empty and holds no priors.json: choose an "
            "empty or new folder (nothing was written)"
        )
    if not cmd.overwrite:
        raise FileExistsError(f"{out} holds priors already (use --overwrite)")


def _run_priors(cmd: Priors) -> int:
    from .estimators import EstimatorKind, EstimatorOptions, run_estimator

    _priors_output(cmd)
    summary = run_estimator(
        cmd.images,
        cmd.output,
        database_path=cmd.database,
        options=EstimatorOptions(
            estimator=EstimatorKind(cmd.estimator),
            max_people=cmd.max_people,
            min_person_size_px=cmd.min_person_size_px,
            detector_levels=cmd.detector_levels,
            show_progress=not cmd.no_progress,
        ),
    )
    sys.stdout.write(
        f"{summary.num_persons} people in "
        f"{summary.num_images_with_people}/{summary.num_images} "
        f"images -> {summary.priors_path} ({summary.seconds:.0f} s)\n"
    )
    for names, reason in _by_reason(summary.skipped):
        sys.stdout.write(f"  skipped {names}: {reason}\n")
    return 0


MAX_LISTED = 6
"""A summary line lists at most this many items; longer lists are counted."""


def _people_links(links: Sequence[tuple[int, int]]) -> str:
    """A pair's person links for the summary table: listed when few, counted when
    many (static cameras hold every instant's people in one view)."""
    if len(links) <= MAX_LISTED:
        return str(list(links))
    return f"{len(links)} people linked"


def _by_reason(reasons: Mapping[str, str]) -> list[tuple[str, str]]:
    """(names, reason) with the names that share a reason on one line: a static
    camera's instants, or a folder of images without people, are one line each."""
    grouped: dict[str, list[str]] = {}
    for name, reason in reasons.items():
        grouped.setdefault(reason, []).append(name)
    out = []
    for reason, names in grouped.items():
        if len(names) == 1:
            out.append((names[0], reason))
        elif len(names) <= MAX_LISTED:
            out.append((f"{len(names)} images ({', '.join(names)})", reason))
        else:
            out.append((f"{len(names)} images ({names[0]} ... {names[-1]})", reason))
    return out


def _run_frames(cmd: Frames) -> int:
    from .frames import extract_frames

    summary = extract_frames(
        cmd.videos, cmd.output, cmd.offsets, cmd.instants, max(1, cmd.step)
    )
    sys.stdout.write(
        f"{len(summary.written)} frames ({len(summary.instants)} instants x "
        f"{len(cmd.videos)} cameras) -> {summary.output_dir}; next: colmap-vc "
        f"augment DB --priors P --static-cameras '{summary.static_cameras}'\n"
    )
    return 0


def _run_augment(cmd: Augment) -> int:
    from .augment import run

    if cmd.image_path is not None and not cmd.image_path.is_dir():
        raise FileNotFoundError(f"image folder not found: {cmd.image_path}")
    summary = run(cmd.database, cmd.priors, cmd.options)
    lines = [
        "| image 1 | image 2 | people | VCs | inliers | ratio | co-visible | virtual | "
        "keypoint | classic inliers |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for p in summary.pairs:
        k = p.num_by_kind
        lines.append(
            f"| {p.image_name1} | {p.image_name2} | "
            f"{p.association_method} {_people_links(p.association)} | {p.num_vcs} | "
            f"{p.num_inliers} | {p.inlier_ratio:.2f} | "
            f"{k.get('covisible', 0)} | {k.get('virtual', 0)} | "
            f"{k.get('keypoint', 0)} | {p.num_classic_inliers}/{p.num_classic} |"
        )
    sys.stdout.write("\n".join(lines) + "\n")
    for names, reason in _by_reason(summary.skipped_images):
        sys.stdout.write(f"skipped {names}: {reason}\n")
    for person, reason in summary.left_out_people.items():
        sys.stdout.write(f"left out {person}: {reason}\n")
    stages = ", ".join(f"{k} {v:.2f} s" for k, v in summary.timings_s.items())
    sys.stdout.write(
        f"{summary.num_verified_pairs}/{len(summary.pairs)} pairs verified; {stages}"
        f"{' (dry run: nothing written)' if summary.dry_run else ''}\n"
    )
    return 0


def _run_map(cmd: Map) -> int:
    from .mapping import run

    options = cmd.options
    if cmd.gba:
        options = dataclasses.replace(
            options,
            keypoint_ba_options=dataclasses.replace(
                options.keypoint_ba_options, surface_tracks=True
            ),
        )
    _, summary = run(
        cmd.database,
        cmd.image_path,
        cmd.output_path,
        options,
        overwrite=cmd.overwrite,
        priors_path=cmd.priors,
    )
    sys.stdout.write(
        f"registered {summary.num_registered}/{summary.num_images} images "
        f"({summary.num_models} model(s)); model: {summary.model_dir}\n"
    )
    scale = summary.metric_scale
    if scale is not None:
        sys.stdout.write(
            f"  in metres from the people's size: x{scale.scale:.4g}, "
            f"{scale.describe()}; see metric_scale.json\n"
        )
    elif options.metric_scale:
        sys.stdout.write(f"  scale arbitrary: {summary.no_scale}\n")
    for name, reason in summary.unregistered.items():
        sys.stdout.write(f"  not registered: {name}: {reason}\n")
    for name, how in summary.re_posed.items():
        sys.stdout.write(f"  {name}: {how}\n")
    return 0


def _run_report(cmd: Report) -> int:
    from .report import ReportInputs, build_report

    path = build_report(
        ReportInputs(
            database_path=cmd.database,
            image_dir=cmd.image_path,
            model_path=cmd.model_path,
            gt_model_path=cmd.gt_model_path,
            max_pairs=cmd.max_pairs,
        ),
        cmd.output,
    )
    sys.stdout.write(f"report: {path}\n")
    return 0


def _run_strip(cmd: Strip) -> int:
    from .database import strip

    result = strip(cmd.database, force=cmd.force)
    if not result.had_vcs:
        logger.info("%s has no colmap-vc VCs: nothing to strip", cmd.database)
    elif result.num_user_rows_kept:
        logger.info(
            "%d row(s) changed after augment were kept as they are now (--force)",
            result.num_user_rows_kept,
        )
    return 0


def _run_demo(cmd: Demo) -> int:
    from .demo import run

    summary = run(cmd.out_dir, overwrite=cmd.overwrite)
    sys.stdout.write(
        f"\nDefault dome scene: {summary.scene_dir}\n"
        "Relative pose accuracy against ground truth (all image pairs; an unregistered "
        "image counts as 180 degrees):\n\n"
        f"{summary.table}\n\nTotal time {summary.elapsed_s:.0f} s. "
        f"Metrics: {cmd.out_dir / 'metrics.json'}\n"
        f"Report (open in a browser): {summary.report_path}\n"
        "What this means: docs/quickstart.md\n"
    )
    return 0


COMMANDS: dict[str, Callable[..., object]] = {
    "synth": Synth,
    "frames": Frames,
    "priors": Priors,
    "augment": Augment,
    "map": Map,
    "strip": Strip,
    "eval": Eval,
    "report": Report,
    "demo": Demo,
}
# Each runner takes the command of its key: Any, as a dict cannot say so.
RUNNERS: dict[type, Callable[[Any], int]] = {
    Synth: _run_synth,
    Frames: _run_frames,
    Priors: _run_priors,
    Augment: _run_augment,
    Map: _run_map,
    Strip: _run_strip,
    Eval: _run_eval,
    Report: _run_report,
    Demo: _run_demo,
}


EXIT_OK, EXIT_FAILURE, EXIT_USAGE, EXIT_BUG = 0, 1, 2, 3
EXIT_INTERRUPTED, EXIT_TERMINATED = 130, 143  # 128 + SIGINT, 128 + SIGTERM


class Terminated(BaseException):
    """SIGTERM, raised in the main thread so open transactions roll back."""


def _raise_terminated(signum: int, frame: object) -> None:
    raise Terminated


def run_command(cmd: object) -> int:
    """Run a parsed command: every expected failure is one line and an exit code.

    Exit codes: 0 success; 1 the input, a file or the data did not allow the run;
    3 a bug in colmap-vc; 130 Ctrl-C; 143 SIGTERM (README.md). With ``--verbose``
    the traceback is logged too.
    """
    verbose = bool(getattr(cmd, "verbose", False))
    previous = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        return RUNNERS[type(cmd)](cmd)
    except KeyboardInterrupt:
        logger.error("%s", interrupted_message(cmd, "Ctrl-C"), exc_info=verbose)
        return EXIT_INTERRUPTED
    except Terminated:
        logger.error("%s", interrupted_message(cmd, "SIGTERM"), exc_info=verbose)
        return EXIT_TERMINATED
    except sqlite3.Error as exc:
        logger.error("%s", sqlite_message(exc, cmd), exc_info=verbose)
        return EXIT_FAILURE
    except OSError as exc:
        logger.error("%s", os_message(exc), exc_info=verbose)
        return EXIT_FAILURE
    except (ValueError, RuntimeError) as exc:
        logger.error("%s", exc, exc_info=verbose)
        return EXIT_FAILURE
    except MemoryError:
        logger.error("out of memory: run fewer images at a time")
        return EXIT_FAILURE
    except Exception as exc:
        logger.error(
            "unexpected %s: %s. This is a bug in colmap-vc: please report it with the "
            "output of the same command with --verbose",
            type(exc).__name__,
            exc,
            exc_info=verbose,
        )
        return EXIT_BUG
    finally:
        signal.signal(signal.SIGTERM, previous)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the `colmap-vc` console script."""
    try:
        cmd = tyro.extras.subcommand_cli_from_dict(
            COMMANDS,
            args=list(sys.argv[1:] if argv is None else argv),
            prog="colmap-vc",
            config=(tyro.conf.EnumChoicesFromValues,),
        )
    except SystemExit as exc:  # tyro exits on --help (0) and on usage errors (2)
        return int(exc.code or 0)
    except KeyboardInterrupt:
        return EXIT_INTERRUPTED
    _setup_logging(getattr(cmd, "verbose", False))
    return run_command(cmd)


if __name__ == "__main__":
    sys.exit(main())
