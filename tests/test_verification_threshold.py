"""The pose verification threshold chosen on validation poses."""

from binpick.registration.constants import DEFAULT_MAX_SEEN_THROUGH
from binpick.scene.verification_threshold import THRESHOLD_RANGE, choose_threshold


def test_the_threshold_separates_right_from_wrong_poses():
    right = [0.0, 0.01, 0.02, 0.03, 0.15, 0.22, 0.28, 0.33]
    wrong = [0.43, 0.48, 0.61, 0.64]
    t = choose_threshold(right, wrong)
    assert 0.33 <= t < 0.43  # every right pose kept, every wrong one dropped
    assert t == DEFAULT_MAX_SEEN_THROUGH  # every cut from 0.33 to 0.43 does as well: the prior


def test_a_wrong_pose_weighs_more_than_a_right_one():
    # One wrong pose at 0.4 among right ones: cutting below it loses the right pose at 0.45,
    # worth it at twice the weight; a second right pose above it tips the balance back.
    assert choose_threshold([0.01, 0.02, 0.45], [0.4, 0.7]) < 0.4
    assert choose_threshold([0.01, 0.02, 0.45, 0.5, 0.55], [0.4, 0.7]) >= 0.55


def test_bounds_hold_with_few_poses():
    assert choose_threshold([0.01], []) == DEFAULT_MAX_SEEN_THROUGH  # no wrong pose seen: the prior
    # A wrong pose below the lower bound cannot be cut away: every cut does as well, the prior wins.
    assert choose_threshold([], [0.01]) == DEFAULT_MAX_SEEN_THROUGH
    # The validation poses leave the cut anywhere from 0.1 to 0.5: the prior.
    assert choose_threshold([0.05, 0.1], [0.5, 0.55]) == DEFAULT_MAX_SEEN_THROUGH
    # They say more: every wrong pose from 0.2, right ones up to 0.1: the lower bound.
    assert choose_threshold([0.05, 0.1], [0.2, 0.25, 0.3, 0.31]) == THRESHOLD_RANGE[0]


def test_a_least_support_cut_keeps_poses_above_it():
    from binpick.registration.constants import DEFAULT_MIN_VISIBLE_SUPPORT
    from binpick.scene.verification_threshold import SUPPORT_RANGE

    def cut(right, wrong):
        return choose_threshold(right, wrong, DEFAULT_MIN_VISIBLE_SUPPORT, SUPPORT_RANGE, keep_below=False)

    # Wrong poses up to 0.45, right ones from 0.85: every cut between does as well, the prior.
    assert cut([0.85, 0.9, 0.97], [0.2, 0.45]) == DEFAULT_MIN_VISIBLE_SUPPORT
    # A wrong pose at 0.82: the cut goes above it, as near the prior as the right poses allow.
    t = cut([0.85, 0.9, 0.97], [0.2, 0.82])
    assert 0.82 < t <= 0.85
    # Wrong poses from 0.85 up to 0.92 among right ones from 0.93: the bound holds the cut at 0.9.
    assert cut([0.93, 0.95, 0.97], [0.85, 0.91, 0.92]) == SUPPORT_RANGE[1]
    # No wrong pose seen: the prior, unless it would drop right poses.
    assert cut([0.9], []) == DEFAULT_MIN_VISIBLE_SUPPORT
    assert cut([0.6, 0.9], []) == 0.6
