"""Metric scale from the people: the model in metres.

A structure-from-motion model has no scale; the people in it do. Every person prior
places its keypoints in metres in its camera's frame (the fitted body has a human
size), and the model triangulates the same keypoints (tracks by identity, as the
keypoint bundle adjustment uses them) up to scale. How much larger a person's
skeleton is in the prior than in the model is the scale: each (image, person) gives
the weighted median over pairs of its keypoints of their distance in the prior over
their distance in the model (:func:`skeleton_ratio`), and the model's scale is a
robust mean over them (Hodges-Lehmann).

The skeleton's size, not how far the prior puts it from the camera: a fit from one
image reads a body's size from its proportions and then places it by reprojection,
and the placement adds an error of its own. Against the calibration, the bundled
estimator puts pose2sim's man 4% nearer than his fitted size says, and the
avatar of pose2sim_multi 3% nearer; the skeleton's size is within 1% of the
man's (docs/results.md, "The scale from the skeleton's size instead of its
distance"; before 21c2a2e `map` read the ratio of distances).

What limits it is the body size a fit assumes from 2D evidence: a person fitted 5%
too tall is 5% too large in every view, so the error is shared by a person's views
and averages out only over different people. The reported spread is that of the
(image, person) ratios (a robust standard deviation, relative); ``num_people`` says
over how many identities it was taken. The scale's uncertainty
(:func:`scale_uncertainty`) adds the size error the views share: one person's fit
is only as good as that person is close to the size the fit assumes. Where the
people of one instant disagree by more than that error allows, the uncertainty
is widened by how much more (:func:`people_disagreement`).

On pose2sim_single (one real person, four cameras, five instants) the camera
distances come out within 1% of the calibration, on pose2sim_multi 7-8% long: there
the avatar's fit is 16% larger than she is and the man's within 1%. Real fits err
per person, so the scale is as good as the people's average size. The synthetic
priors err the same way (a size error per person, shared by its views, and a
smaller one per view: docs/synthetic.md).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import pycolmap
from scipy.spatial.transform import Rotation

from .keypoint_tracks import (
    KeypointTracks,
    keypoint_tracks,
    triangulate_tracks,
)
from .structs import BoolArray, FloatArray, IndexArray, PersonPrior, ScenePriors
from .vc_records import VcRecords

logger = logging.getLogger(__name__)

SCALE_FILE = "metric_scale.json"
"""Written next to the model: the scale applied, its spread and its uncertainty."""

PERSON_SIZE_SD = 0.07
"""Relative standard deviation of a fitted person's size, shared by every view of
that person: two parts in quadrature.

- The person against the body the fit assumes: a fit from the image sees a
  body's proportions, not its size, and adult stature varies with a standard
  deviation of about 7 cm within each sex around 1.62-1.76 m, 4-4.5%, and
  about 5.5% over both.
- The fit's own error that repeats over a person's views (another body's
  proportions, the pose): 3.9% rms over the 18 people of the accuracy bench's
  synthetic `fitted` domes and dense scenes, beyond the size drawn for them
  (1.7% with `realistic` priors; measured on the skeleton's size, as the scale
  is read: by the distance from the camera they were 4.5% and 4.0%).

sqrt(5.5^2 + 3.9^2) = 6.7%, taken as 7%: of the two real people measured, one
is 16% off. Against the calibration, with the model's poses replaced by the
calibrated ones, the bundled estimator's skeletons come out: the pose2sim_single
man 1.00 of his size in the median of his views (0.96-1.11), in pose2sim_multi
the same man 0.99 and the avatar 1.16 (1.06-1.22; docs/results.md, "The scale
from the skeleton's size instead of its distance"). With 7% the truth is within
one uncertainty in all 30 of pose2sim_single's per-instant models and in 6 of
pose2sim_multi's 30 (within two in 25): there the man and the avatar average
+7.5%, 1.5 of the 5% two people give. Their 17% apart widens it to 7.1%
(:func:`people_disagreement`), within one in 18 of 30. On the twelve-draw
synthetic domes with
`realistic` and `fitted` priors within one in 34 and two in 46 of 48
(docs/results.md, "Metric scale")."""

TWO_VIEW_POSE_SD_DEG = 3.8
"""Standard deviation, per degree of freedom, of the relative pose of two images
that only their people place (three of rotation, two of the baseline's
direction). pose2sim's two-camera models of one instant (57 of them,
`bench/subsets.py`) had a median pair error of 5.9 deg; the median length of a
3D Gaussian vector is 1.54 standard deviations. Since two images weigh their
surface as any model does, the 58 read 6.0 deg (3.9 per degree of freedom;
kept at 3.8). A two-view model's depths, and so its scale, follow its relative
pose, by more the narrower the baseline (:func:`relative_pose_uncertainty`);
with more images, or with classic matches placing both, the poses are held
better and this term is left out."""


@dataclass(frozen=True, kw_only=True, slots=True)
class MetricScale:
    """The scale that takes a model to metres, and how well the people agree on it."""

    scale: float  # metres per model unit (applied: the model is now in metres)
    spread: float  # relative robust std of the per-(image, person) ratios
    num_person_views: int  # (image, person) ratios the median is taken over
    num_people: int  # distinct identities among them
    uncertainty: float  # relative standard error of scale: the people's size
    # (scale_uncertainty) and the relative pose's part, in quadrature
    relative_pose: float = 0.0  # the relative pose's part (two images placed by
    # their people alone; 0 otherwise): relative_pose_uncertainty
    num_instants: int = 1  # static cameras: the instants the identities stood at
    people_per_instant: int = 0  # the most identities at one instant (static
    # cameras: the people of different instants may be one person; 0: not known)
    disagreement: float = 1.0  # how much more the people disagree than their
    # size errors say: the people's part is widened by it (people_disagreement)

    def describe(self) -> str:
        """The uncertainty as the CLI and the report print it: "+-5.0% (3
        people)", with the relative pose's part where there is one (static
        cameras: :meth:`people`)."""
        pose = (
            f", the relative pose +-{100 * self.relative_pose:.1f}%"
            if self.relative_pose
            else ""
        )
        return f"+-{100 * self.uncertainty:.1f}% ({self.basis()}{pose})"

    def basis(self) -> str:
        """Whom the scale rests on (:meth:`people`), and by how much their
        disagreement widened it, if it did."""
        if self.disagreement > 1.0:
            return (
                f"{self.people()}, widened x{self.disagreement:.1f}: they disagree "
                "on the size"
            )
        return self.people()

    def people(self) -> str:
        """Whom the scale rests on: "3 people"; static cameras "5 identities
        over 5 instants, taken as 1 person" (the people of different instants
        may be one person; the uncertainty counts the most at one instant)."""
        if self.num_instants > 1 and self.people_per_instant:
            n = self.people_per_instant
            return (
                f"{self.num_people} identities over {self.num_instants} instants, "
                f"taken as {n} {'person' if n == 1 else 'people'}"
            )
        return f"{self.num_people} {'person' if self.num_people == 1 else 'people'}"


def scale_uncertainty(spread: float, num_person_views: int, num_people: float) -> float:
    """Relative standard error of the metric scale: the people's shared size error
    (:data:`PERSON_SIZE_SD`), which averages over people, and the views' own
    (``spread``, about their person's), which averages over views, added in
    quadrature. ``num_people`` is the effective number of people, n^2 / sum m_p^2
    for n views of which m_p show person p (a person seen in most views weighs
    most)."""
    if num_person_views < 1 or num_people <= 0:
        raise ValueError("the scale needs at least one view of one person")
    return float(np.sqrt(PERSON_SIZE_SD**2 / num_people + spread**2 / num_person_views))


def people_disagreement(
    values: FloatArray,
    person: IndexArray,
    within: float,
    instant_of: Mapping[int, str] | None = None,
) -> float:
    """How much more the people disagree on the scale than their size errors
    allow: the Birge ratio sqrt(chi^2 / dof), at least 1 (the Particle Data
    Group's scale factor for measurements that disagree beyond their errors).
    A person's scale is the median of its views' ratios, in logs, with the
    variance PERSON_SIZE_SD^2 + within^2 / m_p (m_p views); chi^2 is their
    spread about the inverse-variance weighted mean of the people of the same
    instant, dof the number of people less one per instant. ``instant_of``
    (identity -> instant; static cameras): the people of one instant are
    different people, while those of different instants may be one person,
    whose ratios then agree by more than different people's. 1 when no instant
    has two people.

    The uncertainty rests on a size error per person measured on a few people;
    a person whose fit is far off (pose2sim_multi's avatar, 16% large) shows as a
    disagreement with the others, and the uncertainty then follows what the
    people show, not what they were assumed to."""
    people, which = np.unique(person, return_inverse=True)
    logs = np.log(values)
    r = np.array([np.median(logs[which == k]) for k in range(len(people))])
    var = PERSON_SIZE_SD**2 + within**2 / np.bincount(which)
    when = np.array([(instant_of or {}).get(int(k), "") for k in people])
    chi2, dof = 0.0, 0
    for t in sorted(set(when.tolist())):  # loop over instants (a handful)
        at = when == t
        mean = np.sum(r[at] / var[at]) / np.sum(1.0 / var[at])
        chi2 += float(np.sum((r[at] - mean) ** 2 / var[at]))
        dof += int(at.sum()) - 1
    return max(1.0, float(np.sqrt(chi2 / dof))) if dof else 1.0


def within_person_spread(values: FloatArray, person: IndexArray) -> float:
    """Robust relative spread of the ratios about their own person's median (the
    views' error, without the people's differences); the overall spread when no
    person has two views."""
    people, which = np.unique(person, return_inverse=True)
    medians = np.array([np.median(values[which == k]) for k in range(len(people))])
    counts = np.bincount(which)
    several = counts[which] >= 2
    if not several.any():
        return relative_spread(values, float(np.median(values)))
    return relative_spread(values[several], medians[which[several]])


def relative_spread(values: FloatArray, centre: FloatArray | float) -> float:
    """Robust relative standard deviation of ``values`` about ``centre`` (1.4826
    times the median absolute relative deviation)."""
    return float(1.4826 * np.median(np.abs(values / centre - 1.0)))


def estimate_metric_scale(
    records: VcRecords,
    rec: pycolmap.Reconstruction,
    priors: ScenePriors,
    *,
    min_track_length: int = 3,
    instant_of: Mapping[tuple[str, int], str] | None = None,
    relative_pose_sd_deg: float | None = None,
) -> MetricScale | None:
    """Scale of ``rec`` in metres from its people's keypoints (module doc), their
    tracks by identity from ``records`` (the database's,
    :func:`~colmap_vc.vc_records.read_vc_records`).

    ``priors`` are keyed by the database's image names (for static cameras: the
    merged priors of the representative images). Keypoint tracks seen by fewer than
    ``min_track_length`` registered images (2 in a two-image model, or where no
    track is longer) are too poorly triangulated to use. None when no keypoint of
    a prior person is triangulated. ``instant_of`` (static cameras: the instant of
    each (image name, index) of a merged prior person) tells the uncertainty
    which people stood at one instant: those are different people, while the
    people of different instants may be the same one (their size errors then
    do not average out). ``relative_pose_sd_deg`` (a two-image model placed by
    its people alone: :data:`TWO_VIEW_POSE_SD_DEG`) adds the relative pose's
    part to the uncertainty.
    """
    found = person_keypoints(records, rec, priors, min_track_length)
    if found is None:
        return None
    ratios = _ratios(found.tracks, found.points, found.views)
    if not ratios:
        return None
    name_of, person_views, tracks = found.name_of, found.views, found.tracks
    instants = {  # identity -> its instant ("": one instant)
        ident: (instant_of or {}).get((name_of[image_id], k), "")
        for (image_id, ident), (_, _, k) in person_views.items()
        if (image_id, ident) in ratios
    }
    values = np.array(list(ratios.values()))
    scale = hodges_lehmann(values)
    spread = relative_spread(values, scale)
    person = np.array([ident for _, ident in ratios], dtype=np.int64)
    people, counts = np.unique(person, return_counts=True)
    when = [instants[k] for k in people.tolist()]
    within = within_person_spread(values, person)
    disagreement = people_disagreement(values, person, within, instants)
    sizes = disagreement * scale_uncertainty(
        within, len(values), effective_people(counts, when)
    )
    pose = 0.0
    if relative_pose_sd_deg is not None and found.num_registered == 2:

        def scale_of(model: pycolmap.Reconstruction) -> float:
            again = _ratios(tracks, triangulate_tracks(model, tracks)[0], person_views)
            return hodges_lehmann(np.array(list(again.values()))) if again else np.nan

        pose = relative_pose_uncertainty(rec, scale_of, relative_pose_sd_deg)
    return MetricScale(
        scale=scale,
        spread=spread,
        num_person_views=len(values),
        num_people=len(counts),
        uncertainty=float(np.hypot(sizes, pose)),
        relative_pose=pose,
        num_instants=len(set(when)),
        people_per_instant=max(when.count(t) for t in set(when)),
        disagreement=disagreement,
    )


PersonViews = dict[tuple[int, int], tuple[IndexArray, FloatArray, int]]
"""Per (image id, identity) with a prior person: its observations (indices into
the tracks), the prior's 3D point of each (camera frame, metres) and the prior
person's index in its image."""


@dataclass(frozen=True, kw_only=True, slots=True)
class PersonKeypoints:
    """The people's keypoints of a model: in the priors and triangulated."""

    tracks: KeypointTracks
    points: FloatArray  # (num_tracks, 3) each track's point (model frame)
    views: PersonViews
    name_of: dict[int, str]  # image id -> name
    num_registered: int


def person_keypoints(
    records: VcRecords,
    rec: pycolmap.Reconstruction,
    priors: ScenePriors,
    min_track_length: int = 3,
) -> PersonKeypoints | None:
    """The keypoints of ``rec``'s people that a prior places and the model
    triangulates from at least ``min_track_length`` registered images (fewer
    where the model has fewer, or no track is longer: static cameras with uneven
    instants, three cameras and no instant seen by more than two). None without
    keypoint tracks."""
    views = records.views
    name_of = dict(zip(views.image_ids.tolist(), views.image_names, strict=True))
    registered = np.array(
        sorted(i for i, im in rec.images.items() if im.has_pose and i in name_of),
        dtype=np.int64,
    )
    tracks = keypoint_tracks(records, registered)
    offset = records.num_samples
    if tracks.num_tracks == 0 or tracks.keys is None or offset <= 0:
        return None
    X, counts = triangulate_tracks(rec, tracks)
    longest = int(counts.max()) if len(counts) else 0
    min_track_length = min(min_track_length, max(len(registered), 2), max(longest, 2))
    good = (counts[tracks.track] >= min_track_length) & np.isfinite(
        X[tracks.track]
    ).all(axis=1)
    return PersonKeypoints(
        tracks=tracks,
        points=X,
        views=_person_views(tracks, good, priors, name_of, offset, records.identity),
        name_of=name_of,
        num_registered=len(registered),
    )


def _person_views(
    tracks: KeypointTracks,
    good: BoolArray,
    priors: ScenePriors,
    name_of: Mapping[int, str],
    offset: int,
    identity: Mapping[tuple[int, int], int],
) -> PersonViews:
    """Per (image id, identity) with a prior person: the ``good`` observations of
    its keypoints that the prior places (indices into ``tracks``), the prior's
    3D point of each (camera frame, metres), and the prior person's index.
    ``identity``: (image id, database person id) -> identity
    (:func:`~colmap_vc.vc_records.person_identities`)."""
    assert tracks.keys is not None
    out = {}
    for image_id in np.unique(tracks.image_id[good]):  # loop over images
        name = name_of[int(image_id)]
        if name not in priors.images:
            continue
        obs = np.flatnonzero(good & (tracks.image_id == image_id))
        keys = tracks.keys[tracks.track[obs]]
        persons = priors.images[name].persons
        for ident in np.unique(keys[:, 0]):  # loop over the image's people
            rows = keys[:, 0] == ident
            j = keys[rows, 1] - offset
            image = int(image_id)
            rank = [  # the person the database names first: by its index
                # (anonymous), then by its own id (_prior_person)
                (
                    identity.get((image, k)) != ident,
                    p.person_id is None or identity.get((image, p.person_id)) != ident,
                )
                for k, p in enumerate(persons)
            ]
            k = _prior_person(persons, j, tracks.xy_img[obs[rows]], rank)
            if k is None:
                continue
            p = persons[k]
            assert p.keypoints_cam is not None  # _prior_person checked
            valid = (
                p.keypoints_valid[j]
                if p.keypoints_valid is not None
                else np.ones(len(j), bool)
            )
            if valid.any():
                points = p.keypoints_cam[j[valid]]
                out[(int(image_id), int(ident))] = (obs[rows][valid], points, k)
    return out


def _ratios(
    tracks: KeypointTracks, X: FloatArray, person_views: PersonViews
) -> dict[tuple[int, int], float]:
    """Per (image id, identity) with two keypoints or more: the skeleton's size
    in the prior over the model's (``X``: the tracks' points), the median over
    the pairs of its keypoints of the prior's distance between the two over the
    model's, each pair weighted by its squared length in the prior
    (:func:`skeleton_ratio`)."""
    ratios = {}
    for key, (obs, prior_cam, _) in person_views.items():  # loop over views
        ratio = skeleton_ratio(prior_cam, X[tracks.track[obs]])
        if np.isfinite(ratio):
            ratios[key] = ratio
    return ratios


def skeleton_ratio(prior: FloatArray, model: FloatArray) -> float:
    """How much larger one person's keypoints are in the prior (metres) than in
    the model: the weighted median over every pair of keypoints of the ratio of
    their distances, each pair weighted by its squared length in the prior (a
    triangulated point's error is about the same for every keypoint, so a
    pair's relative error falls with its length and its log ratio's variance
    with the length squared). Distances, not positions: the fit's rotation and
    translation do not enter. NaN with fewer than two keypoints."""
    prior, model = np.asarray(prior, np.float64), np.asarray(model, np.float64)
    a, b = np.triu_indices(len(prior), 1)
    d_prior = np.linalg.norm(prior[a] - prior[b], axis=1)
    d_model = np.linalg.norm(model[a] - model[b], axis=1)
    ok = (d_prior > 0) & (d_model > 0) & np.isfinite(d_model)
    if not ok.any():
        return float("nan")
    return weighted_median(d_prior[ok] / d_model[ok], d_prior[ok] ** 2)


def weighted_median(values: FloatArray, weights: FloatArray) -> float:
    """The value at which the weights below reach half the total (the lower
    one on a tie)."""
    order = np.argsort(values, kind="stable")
    cumulative = np.cumsum(np.asarray(weights, np.float64)[order])
    return float(values[order][np.searchsorted(cumulative, 0.5 * cumulative[-1])])


def relative_pose_uncertainty(
    rec: pycolmap.Reconstruction,
    scale_of: Callable[[pycolmap.Reconstruction], float],
    sd_deg: float,
) -> float:
    """Relative standard error of a two-image model's scale from its relative
    pose: ``scale_of`` (the scale a model gives) on copies of ``rec`` whose second
    image (by name) is turned by +-``sd_deg`` about each of its axes, or moved by
    as much about the first camera in the two directions across the baseline;
    the central differences, one per degree of freedom, in quadrature. A
    degree of freedom whose copy gives no scale counts as nothing."""
    first, second = sorted(
        (i for i, im in rec.images.items() if im.has_pose),
        key=lambda i: rec.image(i).name,
    )
    T1 = rec.image(first).cam_from_world().matrix()
    T2 = rec.image(second).cam_from_world().matrix()
    c1 = -T1[:, :3].T @ T1[:, 3]
    c2 = -T2[:, :3].T @ T2[:, 3]
    baseline = c2 - c1
    # Two directions across the baseline: the orthogonal complement of its
    # direction (the last two right singular vectors).
    across = np.linalg.svd(baseline[None, :] / np.linalg.norm(baseline))[2][1:]
    step = np.radians(sd_deg)
    poses = []  # (R, centre) of the second image, in pairs +- step
    for axis in np.eye(3):  # turned about its own axes (camera frame)
        for sign in (1.0, -1.0):
            R = Rotation.from_rotvec(sign * step * axis).as_matrix() @ T2[:, :3]
            poses.append((R, c2))
    for axis in across:  # moved about the first camera, across the baseline
        for sign in (1.0, -1.0):
            turn = Rotation.from_rotvec(sign * step * axis).as_matrix()
            poses.append((T2[:, :3], c1 + turn @ baseline))
    base = scale_of(rec)
    scales = []
    for R, c in poses:  # loop over 10 copies
        copy = pycolmap.Reconstruction(rec)
        copy.frame(copy.image(second).frame_id).rig_from_world = pycolmap.Rigid3d(
            pycolmap.Rotation3d(R), -R @ c
        )
        scales.append(scale_of(copy))
    ds = (np.array(scales[0::2]) - np.array(scales[1::2])) / (2.0 * base)
    return float(np.sqrt(np.nansum(ds**2)))


def effective_people(counts: IndexArray, instants: Sequence[str]) -> float:
    """How many people's independent size errors the scale averages: at each
    instant n^2 / sum m_p^2 over its people (n views, m_p of person p; a person
    seen in most views weighs most), the largest over the instants. The people
    of one instant are different people; those of different instants may be the
    same person, whose size error then repeats (a static camera's videos)."""
    counts = np.asarray(counts, dtype=np.float64)
    when = np.asarray(instants)
    return max(
        float(counts[when == t].sum() ** 2 / np.sum(counts[when == t] ** 2))
        for t in sorted(set(when.tolist()))
    )


def _prior_person(
    persons: Sequence[PersonPrior],
    j: IndexArray,
    xy: FloatArray,
    rank: Sequence[tuple[bool, bool]],
) -> int | None:
    """The index of the prior person whose keypoints ``j`` are at ``xy``: a VC
    keypoint is its prior's 2D keypoint. None: no such person (or it has no 3D
    keypoints).

    Several people can have the same keypoints: a static camera's view holds
    every instant's people, and a person who stood still, or a repeated video
    frame, is detected where they were. The people are tried in the order of
    ``rank`` (a stable sort, least first): how surely the database names each one.
    Its person id is the prior's index for an anonymous person (whose prior
    `map` may since have given an identity) and the prior's own id otherwise."""
    order = sorted(range(len(persons)), key=lambda k: rank[k])
    for k in order:  # loop over the image's people (a handful)
        p = persons[k]
        if p.keypoints_xy is None or p.keypoints_cam is None:
            continue
        if len(j) and (j.min() < 0 or j.max() >= len(p.keypoints_xy)):
            continue
        if len(j) and np.abs(p.keypoints_xy[j] - xy).max() < 0.5:
            return k
    return None


def hodges_lehmann(values: FloatArray, max_pairs: int = 1_000_000) -> float:
    """The median of the averages of all pairs of ``values`` (each with itself
    too): a location estimate with a 29% breakdown point. Above ``max_pairs``
    pairs, a fixed random sample of them (the same values, the same estimate)."""
    v = np.sort(np.asarray(values, dtype=np.float64).ravel())
    if v.size == 0:
        raise ValueError("hodges_lehmann needs at least one value")
    if v.size * (v.size + 1) // 2 <= max_pairs:
        i, j = np.triu_indices(v.size)
    else:  # values are sorted, so the subset does not depend on their order
        i, j = np.random.default_rng(0).integers(0, v.size, size=(2, max_pairs))
    return float(np.median((v[i] + v[j]) / 2.0))


def apply_metric_scale_inplace(
    rec: pycolmap.Reconstruction, estimate: MetricScale
) -> None:
    """Scale the model (cameras' positions and points) to metres."""
    rec.transform(pycolmap.Sim3d(estimate.scale, pycolmap.Rotation3d(), np.zeros(3)))


def read_metric_scale(model_dir: Path) -> MetricScale | None:
    """``metric_scale.json`` beside a model, or None: the model's scale is
    arbitrary. A file written before the uncertainty was reported gets it from
    its spread and people."""
    path = Path(model_dir) / SCALE_FILE
    if not path.is_file():
        return None
    try:
        info = json.loads(path.read_text())
        if "uncertainty" not in info:
            info["uncertainty"] = scale_uncertainty(
                info["spread"], info["num_person_views"], info["num_people"]
            )
        return MetricScale(**info)
    except (ValueError, KeyError, TypeError) as error:
        raise ValueError(
            f"{path} is not a metric scale `map` wrote ({error!r}); delete it "
            "or map again"
        ) from error


def write_metric_scale(model_dir: Path, estimate: MetricScale) -> Path:
    """``metric_scale.json`` next to the model."""
    path = Path(model_dir) / SCALE_FILE
    path.write_text(json.dumps(asdict(estimate), indent=2) + "\n")
    return path
