"""The report's figures say which way is good and what the target is, and say when identity cannot
be judged."""

from persona.dag.report import figure_rows, identity_caveat, met, targets_summary


def evaluation(to_b: float, to_a: float) -> dict:
    signals = ("mouth_open", "eye_open")
    return {"frames": 10, "bridged_frames": 0,
            "identity": {"fraction_b_not_a": 0.0, "fraction_b_not_a_composite": 0.0, "mean_distance_to_b": to_b, "mean_distance_to_a": to_a,
                         "frames_without_face": 0},
            "expression": {k: 0.9 for k in signals},
            "amplitude": {"mouth_open": {"gain": 0.8, "r": 0.9, "driver_range": 0.2, "gain_interval": [0.7, 0.9]},
                          "eye_open": {"gain": 0.3, "r": 0.5, "driver_range": 0.02}},
            "gaze": {"face_alone": {"along": {"gain": 0.5, "r": 0.9, "driver_range": 0.3},
                                    "across": {"gain": 0.2, "r": 0.1, "driver_range": 0.04}}},
            "held": {"mouth_open": {"driver": 0.1, "output": 0.05, "composite": -0.02}},
            "stability": {"jitter_ratio": 0.9, "colour_change_ratio": 0.5, "texture_change_ratio": 0.2},
            "composite": {"blend": {"colour_step": 20.0, "gradient_ratio": 1.2}},
            "self_reenactment": {"psnr_db": 24.0, "ssim": 0.76, "psnr_db_composite": 27.5, "ssim_composite": 0.86,
                                 "registration_composite": {"all": 1.5, "jaw": 3.5},
                                 "registration_posed": {"all": 0.9, "jaw": float("nan")}}}


def test_every_figure_says_what_is_good():
    rows = figure_rows(evaluation(0.3, 0.9))
    assert len(rows) == 28  # 9 identity, 2 + 2 expression, 2 gaze, 1 held, 3 stability, 2 composite, 7 self-reenactment
    for label, _, guide, _ in rows[1:]:  # all but the frame count
        assert "better" in guide or "target" in guide or "= " in guide, label
    guides = dict((r[0], r[2]) for r in rows)
    assert guides["self-reenactment psnr_db"] == "higher is better; target ≥ 25"  # the face alone
    assert guides["self-reenactment psnr_db_composite"] == "higher is better; target ≥ 27"
    assert guides["self-reenactment ssim"] == "higher is better"  # no target of its own
    assert "target ≤ 3" in guides["self-reenactment landmark registration (composite.mp4): jaw"]
    motion = "self-reenactment landmark registration (the motion's fiducials)"
    assert "target" not in guides[f"{motion}: all"]  # the targets are the composite's
    assert f"{motion}: jaw" not in guides  # the 49 fiducials have no jaw line
    held = dict((r[0], r[1]) for r in rows)["held expression: mouth open (driver / face alone / composite, IOD)"]
    assert held == "+0.100 / +0.050 / -0.020"
    guides = dict((r[0], r[2]) for r in rows)
    assert "95 % interval 0.70-0.90" in guides["expression gain (output / driver): mouth open"]
    assert "interval" not in guides["expression gain (output / driver): eye open"]  # none given


def test_identity_caveat_when_dlib_sees_one_person_or_the_puppet_is_the_driver():
    assert identity_caveat(evaluation(0.3, 0.9)) is None  # B, and not A: identity can be judged
    text = identity_caveat(evaluation(0.3, 0.4))  # self-reenactment, or synthetic faces
    assert "cannot judge identity" in text
    # B's photos and A's apart (version 7 on): an output near both is a figure to judge, not a caveat
    near_both = evaluation(0.36, 0.59)
    near_both["identity"]["distance_b_to_a"] = 0.74
    assert identity_caveat(near_both) is None
    rows = {r[0]: r for r in figure_rows(near_both)}
    assert rows["frames that are B and not A"][3] == (0.95, None)
    near_both["identity"]["distance_b_to_a"] = 0.45  # dlib sees B's photos and A's as one person
    assert "cannot judge identity" in identity_caveat(near_both)
    own = {**evaluation(0.3, 0.4), "identity": {"judged": False, "frames_judged": 0, "frames_without_face": 0}}
    assert "the puppet is the driver" in identity_caveat(own)
    rows = {r[0]: r for r in figure_rows(own)}  # no identity figure, no target for one
    assert rows["frames that are B and not A"][1] is None and rows["frames that are B and not A"][3] is None


def test_each_target_is_marked_met_or_not():
    """Known answers: a gain of 0.8 meets 0.7-1.4, the face alone's PSNR of 24 dB misses 25, the composite's
    27.5 meets 27 and its SSIM of 0.86 misses 0.88, a jaw registered at 3.5 % misses 3 and all points at 1.5
    meet 2, a seam's step of 20 grey levels misses 7.7, a gaze gain of 0.5 along the eye misses 0.7-1.4 where the
    driver's irises range over 0.3 eye widths, and has no target across it, where they range over 0.04, nor apart
    where the driver's eyes turn apart no more than 1.3 times the measure's noise (it has where they stand at 4); the
    eye gain of 0.3 has no target where the driver's eyes range over 0.02 IOD (< 0.05),
    nor has "B and not A" where dlib sees B and A as one person (0.3 and 0.4 from the output)."""
    assert met(0.8, (0.7, 1.4)) and not met(1.5, (0.7, 1.4)) and met(0, (None, 0)) and met(0.3, None) is None
    rows = {r[0]: r for r in figure_rows(evaluation(0.3, 0.4))}
    assert met(*rows["expression gain (output / driver): mouth open"][1::2])
    assert rows["expression gain (output / driver): eye open"][3] is None
    assert rows["frames that are B and not A"][3] is None
    assert not met(*rows["self-reenactment psnr_db"][1::2])
    assert met(*rows["self-reenactment psnr_db_composite"][1::2])
    assert met(*rows["self-reenactment landmark registration (composite.mp4): all"][1::2])
    assert rows["gaze gain (face alone): across the eye"][3] is None
    noisy = {"gaze": {"face_alone": {"apart": {"gain": 0.1, "r": 0.1, "driver_range": 0.2, "driver_over_noise": 1.3}}}}
    apart = "gaze gain (face alone): the eyes apart (the right one's offset along less the left one's)"
    _, _, guide, target = {r[0]: r for r in figure_rows({**evaluation(0.3, 0.4), **noisy})}[apart]
    assert target is None and "spread 1.3 times it, under 3.0" in guide  # their parting is the measure's noise
    turning = {"gaze": {"face_alone": {"apart": {**noisy["gaze"]["face_alone"]["apart"], "driver_over_noise": 4.0}}}}
    assert {r[0]: r for r in figure_rows({**evaluation(0.3, 0.4), **turning})}[apart][3] == (0.7, 1.4)
    summary = targets_summary(list(rows.values()))
    assert summary.startswith("9 of 14 targets met; not met: ")
    assert "gaze gain (face alone): along the eye 0.50" in summary
    assert "colour step" in summary and "psnr_db 24.00" in summary and "ssim_composite 0.86" in summary
    assert "(composite.mp4): jaw 3.50" in summary
    near = targets_summary([("eye gain", 0.696, "", (0.7, 1.4)), ("brow gain", 0.6996, "", (0.7, 1.4))])
    # never "0.70" or "0.700": they missed
    assert near == "0 of 2 targets met; not met: eye gain 0.696; brow gain 0.6996."


def test_the_mouth_correlation_has_a_target_only_where_the_drivers_mouth_opens():
    """The mouth's correlation with the driver is judged against 0.85 where the driver's mouth ranges over
    0.2 IOD; over 0.01 (lips that stay shut: dlib's noise) it has no target, as its gain has none."""
    ev = evaluation(0.3, 0.9)
    ev["expression"]["mouth_open"] = 0.5
    row = {r[0]: r for r in figure_rows(ev)}["expression correlation: mouth open"]
    assert row[3] == (0.85, None) and met(row[1], row[3]) is False
    ev["amplitude"]["mouth_open"]["driver_range"] = 0.01
    row = {r[0]: r for r in figure_rows(ev)}["expression correlation: mouth open"]
    assert row[3] is None and "0.010 IOD, under 0.05" in row[2]
