"""`colmap-vc augment`: priors -> VC matching -> verification -> the COLMAP database.

:func:`compute_virtual_correspondences` is the pure stage (no I/O) usable inside any
pycolmap workflow; :func:`run` reads the database and priors, calls it and writes the
result in one transaction (or only reports, with ``dry_run``).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import pycolmap
from tqdm import tqdm

from . import __version__, database, outputs
from .association import AssociationOptions, LinkEvidence, PersonCue, associate
from .executor import ExecutorKind, ExecutorOptions, check_options, open_executor
from .matching import (
    MatchingOptions,
    PersonMatches,
    PersonObservations,
)
from .pair_selection import select_pairs
from .priors import focal_mismatches, read_priors
from .static_cameras import (
    merge_priors,
    parse_static_cameras,
    warn_if_static_cameras,
)
from .structs import (
    FloatArray,
    IndexArray,
    PairGeometry,
    PairVcMatches,
    ScenePriors,
    VcKeypoints,
)
from .vc_output import Candidate, PairReport, assemble
from .vc_pairs import (
    PairContext,
    VerifyTask,
    concat_matches,
    in_stored_order,
    link_pairs,
    observe_image,
    person_cues,
    template_samples,
    verify_task,
    verify_tasks,
)
from .verification import (
    Verification,
    VerificationOptions,
    cycle_inconsistent_pairs,
    inverted,
)
from .visibility_check import UnseenPerson, check_visibility

logger = logging.getLogger(__name__)

Pair = tuple[int, int]


@dataclass(frozen=True, kw_only=True, slots=True)
class AugmentOptions:
    """Options of `colmap-vc augment`."""

    matching: MatchingOptions = field(default_factory=MatchingOptions)
    """How VCs are found."""
    verification: VerificationOptions = field(default_factory=VerificationOptions)
    """How VCs are verified."""
    use_classic_matches: bool = True
    """Verify jointly with the pair's classic matches where there are any."""
    min_num_vcs: int = 15
    """Pairs with fewer candidate VCs are skipped."""
    max_classic_inliers: int = 100
    """Pairs whose classic two-view geometry already has this many inliers get no
    VCs: SIFT is far more precise than any human prior where views overlap (0: add
    VCs to every pair)."""
    association: AssociationOptions = field(default_factory=AssociationOptions)
    """How anonymous people are associated across views (colmap_vc.association)."""
    max_link_vcs: int = 100
    """VCs per person link verified on their own when associating (an even
    subsample). The link's inlier ratio enters the association through a log term
    whose slope is about 1 (association._unary): at 100 VCs its binomial noise is
    0.03 (ratios 0.88 on right and wrong links alike), a hundredth of a nat against
    the 0.25 margin a link must win by; its one-person pose differs from the
    400-VC pose by a median 15 deg, inside the 45 deg pose noise the association
    assumes. A link costs 5 ms instead of 14 (bench/scale.py, "link")."""
    max_classic_disagreement_deg: float = 20.0
    """Classic matches join a pair's verification only when their own relative pose
    agrees with the VCs' within this (else a few spurious SIFT inliers could steer
    the pair): the VC pose noise (association.pose_sigma_deg)."""
    max_partners: int | None = 15
    """Past this many images plus one, each image gets VCs with this many partners
    only (smallest view angle the meshes predict, plus what connects the view
    graph): time grows with the images, not the pairs. 15 keeps every pair of a
    16-view scene, the size every accuracy benchmark measures; bench/scale.py
    measures the cost against all pairs. None: every pair."""
    max_cycle_error_deg: float = 35.0
    """A verified pair whose rotation breaks most of the view triplets it closes by
    more than this is dropped (sqrt(3) x the one-pair pose noise of 20 deg)."""
    static_cameras: str | None = None
    """Images from static cameras: a regular expression whose first capturing
    group, searched in the image name, names the physical camera (e.g.
    '(cam\\d+)_'); each camera then has one pose constrained by every instant, and
    people of different instants never match (docs/real-data.md)."""
    executor: ExecutorKind = ExecutorKind.AUTO
    """Where the per-pair stages run: auto (local processes for a few hundred pairs
    or more), serial, processes, or dask (a dask.distributed cluster, --scheduler;
    docs/scaling.md). Every executor writes the same database."""
    workers: int | None = None
    """Local worker processes (default: the machine's cores)."""
    scheduler: str | None = None
    """Address of a dask.distributed scheduler, with --executor dask."""
    dry_run: bool = False
    """Compute and report, write nothing."""
    show_progress: bool = True
    """Progress bar on stderr."""


@dataclass(frozen=True, kw_only=True, slots=True)
class VirtualCorrespondences:
    """Output of :func:`compute_virtual_correspondences` (what gets written)."""

    keypoints: list[VcKeypoints]
    pairs: list[PairVcMatches]
    geometries: dict[Pair, PairGeometry]
    classic_inliers: dict[Pair, IndexArray]
    associations: list[database.PersonAssociation]
    reports: list[PairReport]
    skipped_images: dict[str, str]  # image name -> reason
    unseen_people: tuple[UnseenPerson, ...] = ()
    """Identities the visibility check unlinked (colmap_vc.visibility_check)."""


@dataclass(frozen=True, kw_only=True, slots=True)
class AugmentSummary:
    """What `augment` did."""

    database_path: Path
    dry_run: bool
    num_images: int
    num_images_with_priors: int
    skipped_images: dict[str, str]
    pairs: list[PairReport]
    timings_s: dict[str, float]
    write: database.WriteSummary | None
    left_out_people: dict[str, str] = field(default_factory=dict)
    """Identities the visibility check unlinked ("person N", as the association
    numbered them, -> reason with their detections)."""

    @property
    def num_verified_pairs(self) -> int:
        """Pairs that got a verified two-view geometry."""
        return sum(p.verified for p in self.pairs)


def compute_virtual_correspondences(
    views: database.DatabaseViews,
    priors: ScenePriors,
    options: AugmentOptions | None = None,
    classic_keypoints: Mapping[int, FloatArray] | None = None,
    classic_matches: Mapping[Pair, IndexArray] | None = None,
    timings: dict[str, float] | None = None,
    solved_pairs: set[Pair] | None = None,
    person_groups: Mapping[tuple[str, int], str] | None = None,
) -> VirtualCorrespondences:
    """Find, associate and verify VCs for every pair of images with priors.

    Args:
        views: images and cameras (from :func:`database.read_views`).
        priors: the human priors, by image name.
        options: augment options.
        classic_keypoints: classic keypoints (N, 2) by image id, for joint verification.
        classic_matches: raw classic matches (M, 2) by pair (id1 < id2).
        timings: filled with seconds per stage when given.
        solved_pairs: pairs (id1 < id2) classic matching already solved: no VCs.
        person_groups: (image name, person index) -> instant; people of different
            instants never match (static cameras, :mod:`colmap_vc.static_cameras`).
    """
    options = options or AugmentOptions()
    timings = timings if timings is not None else {}
    classic_keypoints = classic_keypoints or {}
    classic_matches = classic_matches or {}
    name_to_idx = {n: i for i, n in enumerate(views.image_names)}
    skipped = {
        n: "no priors for this image"
        for n in views.image_names
        if n not in priors.images
    }
    skipped.update(
        {
            n: "no person in the priors"
            for n, p in priors.images.items()
            if not p.persons
        }
    )
    names = [
        n for n in views.image_names if n in priors.images and priors.images[n].persons
    ]

    # Everything below runs in image-name order, never in the database's order:
    # the same images give the same VCs whatever order COLMAP wrote them in.
    names = sorted(names)
    t0 = time.perf_counter()
    samples = template_samples(priors, options.matching.num_samples)
    observations: dict[str, list[PersonObservations]] = {}
    cues: list[PersonCue] = []
    groups_of: dict[str, list[str]] = {}
    for name in tqdm(
        names, desc="observe", disable=not options.show_progress, leave=False
    ):
        camera = views.cameras[int(views.camera_ids[name_to_idx[name]])]
        groups = None
        if person_groups:
            groups = [
                person_groups.get((name, k), "")
                for k in range(len(priors.images[name].persons))
            ]
        prior, observations[name] = observe_image(
            priors, name, camera, samples, options.matching, groups
        )
        cues += person_cues(name, prior, groups)
        if groups:
            groups_of[name] = groups
    timings["observe"] = time.perf_counter() - t0

    def camera_of(name: str) -> pycolmap.Camera:
        return views.cameras[int(views.camera_ids[name_to_idx[name]])]

    def id_of(name: str) -> int:
        return int(views.image_ids[name_to_idx[name]])

    def pair_ids(n1: str, n2: str) -> tuple[int, int]:
        return (
            (id_of(n1), id_of(n2)) if id_of(n1) < id_of(n2) else (id_of(n2), id_of(n1))
        )

    t0 = time.perf_counter()
    name_pairs = [
        (n1, n2)
        for n1, n2 in select_pairs(
            priors.images,
            names,
            options.max_partners,
            # Two meshes' orientation errors, each at the VC pose noise.
            max_disagreement_deg=2 * options.association.pose_sigma_deg,
        )
        if not (solved_pairs and pair_ids(n1, n2) in solved_pairs)
    ]
    cache: dict[tuple[str, str, int, int], PersonMatches] = {}
    links: list[LinkEvidence] = []
    cameras = {n: camera_of(n) for n in names}
    executor_options = ExecutorOptions(
        executor=options.executor,
        workers=options.workers,
        scheduler=options.scheduler,
    )
    with open_executor(
        executor_options, len(name_pairs), options.show_progress
    ) as executor:
        linked = executor.map(
            link_pairs,
            PairContext(
                observations=observations,
                cameras=cameras,
                options=options,
                groups=groups_of,
            ),
            name_pairs,
            "person links",
        )
        for (n1, n2), (pair_links_, matches) in zip(name_pairs, linked, strict=True):
            links += pair_links_
            cache.update({(n1, n2, a, b): m for (a, b), m in matches.items()})
        timings["link"] = time.perf_counter() - t0
        association, unseen = check_visibility(
            associate(cues, links, options.association),
            cues,
            cameras,
            options.association,
        )
        timings["associate"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        tasks: list[VerifyTask] = []
        stored_order: list[tuple[IndexArray, int]] = []
        cats: list[tuple[IndexArray, ...]] = []
        for n1, n2 in sorted(association.links):
            # Identities given in the priors link every pair of images that share
            # a person, also pairs no VC was computed for (left to classic
            # matching, or beyond the selected partners).
            pair_links = [
                (a, b)
                for a, b in association.links[(n1, n2)]
                if (n1, n2, a, b) in cache
            ]
            if not pair_links:
                continue
            cat = concat_matches([(a, b, cache[(n1, n2, a, b)]) for a, b in pair_links])
            if len(cat[0]) < options.min_num_vcs:
                continue
            id1, id2 = pair_ids(n1, n2)
            cm = (
                classic_matches.get((id1, id2), np.zeros((0, 2), np.int64))
                if options.use_classic_matches
                else np.zeros((0, 2), np.int64)
            )
            if id1 != id_of(n1):
                cm = cm[:, ::-1]  # classic matches are stored in id order
            task, canonical = verify_task(
                n1,
                n2,
                cat,
                observations,
                cm,
                classic_keypoints.get(id_of(n1)),
                classic_keypoints.get(id_of(n2)),
            )
            tasks.append(task)
            stored_order.append((canonical, len(cm)))
            cats.append(cat)
        results = executor.map(
            verify_tasks,
            PairContext(observations={}, cameras=cameras, options=options),
            tasks,
            "verify",
        )
    verified: dict[tuple[str, str], tuple[Verification, tuple[IndexArray, ...], int]]
    verified = {}
    failed: dict[tuple[str, str], tuple[tuple[IndexArray, ...], str]] = {}
    for task, result, (canonical, num_cm), cat in zip(
        tasks, results, stored_order, cats, strict=True
    ):
        n1, n2 = task.image_name1, task.image_name2
        result = in_stored_order(result, canonical)
        if result.geometry is None:
            failed[(n1, n2)] = (cat, "the associated people's VCs do not verify")
            continue
        verified[(n1, n2)] = (result, cat, num_cm)
    dropped = cycle_inconsistent_pairs(
        {p: v[0].geometry.cam2_from_cam1[:, :3] for p, v in verified.items()},  # type: ignore[union-attr]
        options.max_cycle_error_deg,
    )
    for p, reason in dropped.items():
        logger.info("pair %s / %s dropped: %s", p[0], p[1], reason)
        failed[p] = (verified.pop(p)[1], reason)
    timings["verify"] = time.perf_counter() - t0

    # Back to the database's convention: pairs in image-id order.
    candidates: list[Candidate] = []
    method = association.method
    for (n1, n2), (result, cat, num_classic) in verified.items():
        pl = association.links[(n1, n2)]
        if id_of(n1) > id_of(n2):
            n1, n2, cat = n2, n1, (cat[2], cat[3], cat[0], cat[1], cat[4], cat[5])
            result, pl = inverted(result), [(b, a) for a, b in pl]
        candidates.append(Candidate(n1, n2, result, cat, pl, method, num_classic))
    for (n1, n2), (cat, reason) in failed.items():
        pl = association.links.get((n1, n2), [])
        none = Verification(
            geometry=None,
            vc_is_inlier=np.zeros(len(cat[0]), dtype=bool),
            classic_is_inlier=np.zeros(0, dtype=bool),
        )
        if id_of(n1) > id_of(n2):
            n1, n2, cat = n2, n1, (cat[2], cat[3], cat[0], cat[1], cat[4], cat[5])
            pl = [(b, a) for a, b in pl]
        candidates.append(Candidate(n1, n2, none, cat, pl, method, 0, reason))
    candidates.sort(key=lambda c: pair_ids(c.name1, c.name2))
    timings["match_verify"] = timings["associate"] + timings["verify"]
    t0 = time.perf_counter()
    keypoints, pairs, geometries, classic_inliers, associations, reports = assemble(
        candidates,
        names,
        observations,
        {n: id_of(n) for n in names},
        classic_matches if options.use_classic_matches else {},
    )
    timings["assemble"] = time.perf_counter() - t0
    return VirtualCorrespondences(
        keypoints=keypoints,
        pairs=pairs,
        geometries=geometries,
        classic_inliers=classic_inliers,
        associations=associations,
        reports=reports,
        skipped_images=skipped,
        unseen_people=tuple(unseen),
    )


def run(
    database_path: Path, priors_path: Path, options: AugmentOptions | None = None
) -> AugmentSummary:
    """Augment a COLMAP database with VCs from priors (one transaction)."""
    options = options or AugmentOptions()
    database_path = Path(database_path)
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    check_options(
        ExecutorOptions(
            executor=options.executor,
            workers=options.workers,
            scheduler=options.scheduler,
        )
    )
    views = database.read_views(database_path)
    if not options.dry_run:
        database.check_before_write(database_path)  # before the work, not after
    sizes = {
        name: (views.cameras[int(c)].width, views.cameras[int(c)].height)
        for name, c in zip(views.image_names, views.camera_ids, strict=True)
    }
    priors = read_priors(
        Path(priors_path), known_image_names=views.image_names, image_sizes=sizes
    )
    focal = {
        name: views.cameras[int(c)].mean_focal_length()
        for name, c in zip(views.image_names, views.camera_ids, strict=True)
    }
    if other := focal_mismatches(priors, focal):
        name = min(other)
        logger.warning(
            "the priors of %d image(s) were made with another focal length than "
            "the database's camera (e.g. %s: %.0f px against %.0f px): the "
            "meshes' depth and the people's size follow it; make the priors "
            "again with `colmap-vc priors --database`",
            len(other),
            name,
            *other[name],
        )
    static = None
    groups: dict[tuple[str, int], str] | None = None
    if options.static_cameras:
        static = parse_static_cameras(options.static_cameras, views.image_names)
        priors, groups = merge_priors(priors, static)
    for name in views.image_names:
        if name not in priors.images and (
            static is None or static.representative_of(name) == name
        ):
            logger.warning("no priors for image %s: skipped", name)
    with_priors = [
        int(i)
        for i, n in zip(views.image_ids, views.image_names, strict=True)
        if n in priors.images
    ]
    classic_kp: dict[int, FloatArray] = {}
    classic_m: dict[Pair, IndexArray] = {}
    if options.use_classic_matches:
        classic_kp = {i: database.read_keypoints(database_path, i) for i in with_priors}
        classic_m = database.read_matches(database_path)
    geometries = database.read_two_view_geometries(database_path)
    if static is None:
        warn_if_static_cameras(geometries, views)
    solved: set[Pair] = set()
    if options.max_classic_inliers > 0:
        solved = {
            p
            for p, row in geometries.items()
            if len(row.inlier_matches) >= options.max_classic_inliers
        }
        if solved:
            logger.info(
                "%d pair(s) already solved by classic matching: no VCs there",
                len(solved),
            )
    timings["read"] = time.perf_counter() - t0
    vcs = compute_virtual_correspondences(
        views,
        priors,
        options,
        classic_kp,
        classic_m,
        timings,
        solved_pairs=solved,
        person_groups=groups,
    )
    if static is not None:
        for name in views.image_names:
            rep = static.representative_of(name)
            if rep != name:
                vcs.skipped_images[name] = (
                    f"static camera {static.camera_of[name]}: its people are in "
                    f"{rep}'s view, which stands for every instant of the camera"
                )
    write = None
    if not options.dry_run:
        t0 = time.perf_counter()
        write = database.write_virtual_correspondences(
            database_path,
            vcs.keypoints,
            vcs.pairs,
            vcs.geometries,
            classic_inliers=vcs.classic_inliers,
            persons=vcs.associations,
            run_info={
                "colmap_vc_version": __version__,
                "priors": str(Path(priors_path).resolve()),
                "options": outputs.jsonable(asdict(options)),
                "left_out_people": {
                    f"{d.key[0]} #{d.key[1]}": d.reason
                    for u in vcs.unseen_people
                    for d in u.detections
                },
            },
        )
        timings["write"] = time.perf_counter() - t0
    summary = AugmentSummary(
        database_path=database_path,
        dry_run=options.dry_run,
        num_images=len(views.image_names),
        num_images_with_priors=len(with_priors),
        skipped_images=vcs.skipped_images,
        left_out_people={f"person {u.identity}": u.reason for u in vcs.unseen_people},
        pairs=vcs.reports,
        timings_s=timings,
        write=write,
    )
    with_people = sum(
        1 for n in views.image_names if n in priors.images and priors.images[n].persons
    )
    seen = (  # a static camera's images share one view of its people
        f"{summary.num_images_with_priors}/{summary.num_images} images with priors"
        if static is None
        else f"{summary.num_images_with_priors} static-camera views with priors "
        f"for {summary.num_images} images"
    )
    logger.info(
        "augment%s: %s (%d with people), %d pairs with VCs, "
        "%d verified, %d VCs (%d inliers)",
        " (dry run)" if options.dry_run else "",
        seen,
        with_people,
        len(summary.pairs),
        summary.num_verified_pairs,
        sum(p.num_vcs for p in summary.pairs),
        sum(p.num_inliers for p in summary.pairs),
    )
    return summary
