"""The metric scale's location estimate over the people's per-view size ratios."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from colmap_vc.metric_scale import (
    PERSON_SIZE_SD,
    effective_people,
    hodges_lehmann,
    read_metric_scale,
    scale_uncertainty,
    within_person_spread,
)


def test_hodges_lehmann_is_the_median_of_pair_averages() -> None:
    v = np.array([1.0, 2.0, 4.0])
    # pair averages (each with itself too): 1, 1.5, 2.5, 2, 3, 4 -> median 2.25
    assert hodges_lehmann(v) == pytest.approx(2.25)
    assert hodges_lehmann(np.array([0.9, 1.1])) == pytest.approx(1.0)


def test_size_errors_of_either_sign_average_out_where_the_median_does_not() -> None:
    # A fit a few percent too large or too small in each view (no mass near 1):
    # 7 views too large, 5 too small. The median picks a side, HL does not.
    rng = np.random.default_rng(3)
    e = rng.uniform(0.05, 0.15, 12) * np.r_[np.ones(7), -np.ones(5)]
    v = 1.0 + e
    assert abs(np.median(v) - 1.0) > 0.04
    assert abs(hodges_lehmann(v) - 1.0) < abs(np.median(v) - 1.0) / 2


def test_hodges_lehmann_resists_a_quarter_of_wild_views() -> None:
    v = np.r_[np.random.default_rng(0).normal(1.0, 0.03, 30), np.full(10, 6.0)]
    assert hodges_lehmann(v) == pytest.approx(1.0, abs=0.1)


def test_hodges_lehmann_does_not_depend_on_order_even_when_sampled() -> None:
    v = np.random.default_rng(1).normal(1.0, 0.1, 2000)
    full = hodges_lehmann(v)
    sampled = hodges_lehmann(v, max_pairs=50_000)
    assert sampled == hodges_lehmann(v[::-1], max_pairs=50_000)
    assert sampled == pytest.approx(full, abs=0.005)
    with pytest.raises(ValueError, match="at least one"):
        hodges_lehmann(np.array([]))


def test_uncertainty_averages_the_size_error_over_people_not_views() -> None:
    # One person seen by many views that agree: the person's size error stays.
    assert scale_uncertainty(0.0, 100, 1) == pytest.approx(PERSON_SIZE_SD)
    assert scale_uncertainty(0.01, 100, 1) == pytest.approx(
        np.hypot(PERSON_SIZE_SD, 0.001)
    )
    # Four people: half of it. The views' spread averages over the views.
    assert scale_uncertainty(0.0, 8, 4) == pytest.approx(PERSON_SIZE_SD / 2)
    assert scale_uncertainty(0.2, 4, 4) == pytest.approx(
        np.hypot(PERSON_SIZE_SD / 2, 0.1)
    )
    with pytest.raises(ValueError, match="at least one view"):
        scale_uncertainty(0.0, 0, 1)


def test_views_spread_is_taken_about_each_persons_own_size() -> None:
    # Two people 15% apart, each person's views within about 1% of each other:
    # the views' error is 1%, the people's difference is the size error's.
    rng = np.random.default_rng(5)
    a, b = 1.0 + rng.normal(0, 0.01, 6), 1.15 + rng.normal(0, 0.01, 6)
    values, person = np.r_[a, b], np.r_[np.zeros(6), np.ones(6)].astype(np.int64)
    within = within_person_spread(values, person)
    assert 0.003 < within < 0.02
    overall = 1.4826 * np.median(np.abs(values / np.median(values) - 1.0))
    assert overall > 0.05
    # One view per person: nothing within a person to measure, the overall one.
    single = within_person_spread(values[[0, 6]], np.array([0, 1]))
    assert single == pytest.approx(
        1.4826 * np.median(np.abs(values[[0, 6]] / np.median(values[[0, 6]]) - 1))
    )


def test_people_of_different_instants_may_be_one_person() -> None:
    # Two people seen 4 times each at one instant: two independent sizes.
    assert effective_people(np.array([4, 4]), ["", ""]) == pytest.approx(2.0)
    # One seen 9 times, one once: the first's size is nearly all of it.
    assert effective_people(np.array([9, 1]), ["", ""]) == pytest.approx(100 / 82)
    # A static camera's five instants of one man: five identities, one size.
    assert effective_people(np.array([4] * 5), list("abcde")) == pytest.approx(1.0)
    # Two people at each of two instants: two sizes, not four.
    assert effective_people(np.array([4, 4, 4, 4]), list("aabb")) == pytest.approx(2)


def test_a_scale_file_without_uncertainty_gets_it_from_its_fields(
    tmp_path: Path,
) -> None:
    assert read_metric_scale(tmp_path) is None  # no file: the scale is arbitrary
    old = {"scale": 0.8, "spread": 0.02, "num_person_views": 4, "num_people": 1}
    (tmp_path / "metric_scale.json").write_text(json.dumps(old))
    scale = read_metric_scale(tmp_path)
    assert scale is not None and scale.scale == 0.8
    assert scale.uncertainty == pytest.approx(np.hypot(PERSON_SIZE_SD, 0.01))


def test_a_broken_scale_file_names_itself(tmp_path: Path) -> None:
    (tmp_path / "metric_scale.json").write_text('{"scale": 0.8}')
    with pytest.raises(ValueError, match=r"metric_scale\.json.*spread"):
        read_metric_scale(tmp_path)
    (tmp_path / "metric_scale.json").write_text("{not json")
    with pytest.raises(ValueError, match=r"metric_scale\.json is not a metric scale"):
        read_metric_scale(tmp_path)
