"""The report's figures say which way is good and what the target is, and say when identity cannot
be judged."""

from persona.dag.report import figure_rows, identity_caveat


def evaluation(to_b: float, to_a: float) -> dict:
    signals = ("mouth_open", "eye_open")
    return {"frames": 10, "bridged_frames": 0,
            "identity": {"fraction_b_not_a": 0.0, "fraction_b_not_a_composite": 0.0, "mean_distance_to_b": to_b, "mean_distance_to_a": to_a,
                         "frames_without_face": 0},
            "expression": {k: 0.9 for k in signals},
            "amplitude": {k: {"gain": 0.8, "r": 0.9} for k in signals},
            "stability": {"jitter_ratio": 0.9, "colour_change_ratio": 0.5, "texture_change_ratio": 0.2},
            "composite": {"blend": {"colour_step": 20.0, "gradient_ratio": 1.2}},
            "self_reenactment": {"psnr_db": 26.0, "ssim": 0.76}}


def test_every_figure_says_what_is_good():
    rows = figure_rows(evaluation(0.3, 0.9))
    assert len(rows) == 19  # 8 identity, 2 + 2 expression, 3 stability, 2 composite, 2 self-reenactment
    for label, _, guide in rows[1:]:  # all but the frame count
        assert "better" in guide or "target" in guide or "= " in guide, label
    assert dict((r[0], r[2]) for r in rows)["self-reenactment psnr_db"] == "higher is better; target ≥ 28 dB"


def test_identity_caveat_when_dlib_sees_one_person():
    assert identity_caveat(evaluation(0.3, 0.9)) is None  # B, and not A: identity can be judged
    text = identity_caveat(evaluation(0.3, 0.4))  # self-reenactment, or synthetic faces
    assert "cannot judge identity" in text
