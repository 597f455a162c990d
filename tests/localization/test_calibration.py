"""The calibrated threshold against a brute-force search over every candidate threshold."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from seqvpr.localization.calibration import find_threshold, precision_at
from tests.helpers import examples, raises_one_line


@settings(max_examples=examples(150), deadline=None)
@given(st.lists(st.tuples(st.sampled_from([0.1, 0.2, 0.3, 0.5, 0.9]), st.booleans()), min_size=1, max_size=30),
       st.sampled_from([0.5, 0.8, 0.99, 1.0]))
def test_the_threshold_is_the_lowest_that_reaches_the_target(pairs, target):
    scores, correct = np.array([p[0] for p in pairs]), np.array([p[1] for p in pairs])
    found = find_threshold(scores, correct, target)
    meeting = [t for t in sorted(set(scores)) if precision_at(scores, correct, t)[0] >= target]
    if not meeting:
        assert not found.reached and (scores < found.threshold).all()
        return
    assert found.reached and found.threshold == meeting[0]
    precision, recall = precision_at(scores, correct, found.threshold)
    assert abs(found.precision - precision) < 1e-12 and abs(found.recall - recall) < 1e-12


def test_bad_targets_and_empty_calibrations_are_one_line():
    raises_one_line("target_precision must be in (0, 1]", find_threshold, np.ones(3), np.ones(3, bool), 1.5)
    raises_one_line("no frame of the calibration traversal", find_threshold, np.zeros(0), np.zeros(0, bool), 0.9)


def test_a_threshold_says_where_it_came_from(tmp_path):
    from seqvpr.localization.localizer import (
        LocalizerSettings, calibration_source, store_calibration, stored_threshold,
    )

    settings = LocalizerSettings()
    assert stored_threshold(tmp_path, settings) == (
        0.1, "the default for matching, not calibrated on this map (seqvpr localize --calibrate)")
    record = {"threshold": 0.3, "calibration": "winter", "query_frames": "17:400", "ground_truth": "radius 1f",
              "target_precision": 0.99, "precision": 0.991, "reached": True, "created": "2026-11-26T10:00:00+00:00"}
    assert calibration_source(record) == ("calibrated on winter frames 17:400, ground truth radius 1f, target "
                                          "precision 0.99 reached (0.991), 2026-11-26T10:00:00+00:00")
    assert "NOT reached" in calibration_source({**record, "reached": False})
    store_calibration(tmp_path, settings, record)
    assert stored_threshold(tmp_path, settings) == (0.3, calibration_source({"settings": settings.key(), **record}))
    assert stored_threshold(tmp_path, LocalizerSettings(method="hmm"))[0] == 0.5
