"""``camo study simulate``: simulated participants through the real site over loopback HTTP, then the report."""

from __future__ import annotations

import argparse
import json
import threading

import numpy as np
import pytest
from PIL import Image

from camo_base.errors import CamoError
from study_site import create_app
from study_site.simulate import check_loopback, parse_observer, simulate
from study_site.stimuli import build_stimuli

SIZE = 128


def _texture(rng: np.random.Generator) -> np.ndarray:
    """Green 1/f texture, uint8 (SIZE, SIZE, 3)."""
    f = np.fft.fftfreq(SIZE)
    fr = np.sqrt(f[:, None] ** 2 + f[None, :] ** 2)
    fr[0, 0] = 1.0
    tex = np.real(np.fft.ifft2((rng.normal(size=(SIZE, SIZE)) + 1j * rng.normal(size=(SIZE, SIZE))) / fr))
    t = 0.5 + 0.12 * (tex - tex.mean()) / tex.std() + 0.05 * rng.normal(size=(SIZE, SIZE))
    return (np.clip(np.stack([0.35 * t, 0.75 * t, 0.25 * t], -1), 0, 1) * 255).astype(np.uint8)


def _eval_dir(root, scenes=("sa", "sb")):
    """renders.json with two methods per scene: "red" (a saturated red disc) and "hidden" (no visible object:
    the image is the background, the mask says where the object would be)."""
    rng = np.random.default_rng(0)
    entries = []
    yy, xx = np.mgrid[0:SIZE, 0:SIZE]
    for s in scenes:
        bg = _texture(rng)
        cx, cy = rng.uniform(25, SIZE - 25, 2)
        mask = (yy - cy) ** 2 + (xx - cx) ** 2 < 10 ** 2
        for method in ("red", "hidden"):
            img = bg.copy()
            if method == "red":
                img[mask] = (230, 15, 15)
            d = root / "renders" / f"{s}-{method}"
            d.mkdir(parents=True)
            Image.fromarray(img).save(d / "view_00_obj.png")
            Image.fromarray(bg).save(d / "view_00_bg.png")
            Image.fromarray(mask.astype(np.uint8) * 255).save(d / "view_00_mask.png")
            rel = f"renders/{s}-{method}"
            entries.append({"run": f"{s}-{method}", "scene": s, "object": "disc", "method": method, "ablation": "none",
                            "view": 0, "image": f"{rel}/view_00_obj.png", "background": f"{rel}/view_00_bg.png",
                            "mask": f"{rel}/view_00_mask.png"})
    (root / "renders.json").write_text(json.dumps(entries))


#: The live site's time limit in these tests: short, so hidden objects time out quickly, but long enough for the red
#: disc's decision (see the report test).
LIMIT_S = 4.0


@pytest.fixture()
def live_site(tmp_path):
    """The study app served by werkzeug in a thread on 127.0.0.1 (random port); 4 s trials, 1 practice trial."""
    from werkzeug.serving import make_server

    _eval_dir(tmp_path / "eval")
    build_stimuli([tmp_path / "eval"], tmp_path / "stim", log=lambda m: None)
    app = create_app({"STIMULI_DIR": str(tmp_path / "stim"), "DATABASE_URL": f"sqlite:///{tmp_path / 'study.sqlite'}",
                      "PRACTICE_TRIALS": 1, "TRIAL_TIME_LIMIT_S": LIMIT_S, "ID_HMAC_KEY": "k" * 64, "SECRET_KEY": "s" * 64})
    srv = make_server("127.0.0.1", 0, app, threaded=True)
    th = threading.Thread(target=srv.serve_forever, daemon=True)
    th.start()
    try:
        yield f"http://127.0.0.1:{srv.server_port}", tmp_path
    finally:
        srv.shutdown()
        th.join(10)


def test_simulated_participants_through_the_site_and_the_report(live_site):
    from study_site.analysis import write_report

    url, root = live_site
    n = 12
    res = simulate(url, n, concurrency=12, seed=3, max_seconds=120)
    assert res["completed"] == n and res["n_errors"] == 0, res["errors"]
    assert res["trials"] == n * (1 + 2) and res["formal_trials"] == n * 2
    assert res["stimuli_seen"] <= 2 * 2 + 8  # the observer's map is computed once per image
    rep = write_report(root / "study.sqlite", root / "report", n_boot=50, stimuli_dir=root / "stim")
    trials = rep["trials"]
    formal = trials[~trials["practice"]]
    assert len(trials) == n * 3 and trials["participant"].nunique() == n
    assert not formal["too_fast"].any()
    # a click the observer makes just before the limit can arrive after it on a loaded machine (stored as late,
    # a timeout): rare
    assert int(formal["late"].sum()) <= 2
    assert (formal.loc[~formal["timed_out"], "rt_ms"] <= 1000 * LIMIT_S).all()  # clicks within the limit
    assert (formal.loc[formal["timed_out"], "rt_ms"] >= 1000 * LIMIT_S).all()  # timeouts sent once it had passed
    # what the client was told is what the database holds (one record per stored trial)
    rec = {(r["participant"], r["index"]): r for r in res["records"]}
    assert len(rec) == n * 3
    assert sum(r["hit"] for r in rec.values()) == int(trials["hit"].sum())
    assert sum(r["timed_out"] for r in rec.values()) == int(trials["timed_out"].sum())
    # every cell filled evenly: 4 participants per scene x method
    assert set(formal.groupby(["scene", "method"]).size()) == {n // 2}
    t = rep["table"].set_index("condition")
    # a saturated red disc is found. (Its evidence sits at the verification criterion here -- V 5.9-6.2 against 6:
    # the site serves no object-free view, so the observer uses the image's own statistics, where the disc inflates
    # its own surround -- and the diffusion decision takes ~0.5 s there: the library predicts 4-20 % timeouts within
    # 4 s, 24-51 % within 2.5 s, the former limit. docs/observer.md, "Not done": sets without a background.)
    assert t.loc["red", "confusion_rate"] <= 0.3
    # what the library predicts for these images (same observer, the site's limit, centre start): the site's
    # figures agree within sampling error (6 trials per stimulus; a hidden disc is "found" only where it happens
    # to lie on a salient spot of the texture)
    from evaluation.observer import ObserverConfig, predict_stimulus

    expected, red_times = {}, []
    for e in json.loads((root / "eval" / "renders.json").read_text()):
        img = np.asarray(Image.open(root / "eval" / e["image"]).convert("RGB"))
        mask = np.asarray(Image.open(root / "eval" / e["mask"]).convert("L")) >= 128
        p = predict_stimulus(img, mask, 400, 0, ObserverConfig(time_limit_s=LIMIT_S))
        expected.setdefault(e["method"], []).append(1.0 - p.p_found)
        if e["method"] == "red":
            red_times.append(p.rt_found_s)
    for m, conf in expected.items():
        assert abs(t.loc[m, "confusion_rate"] - np.mean(conf)) <= 0.3, (m, t.loc[m, "confusion_rate"], conf)
    assert t.loc["hidden", "confusion_rate"] - t.loc["red", "confusion_rate"] >= 0.4
    # the site's median time of finds (about 10 finds) lies within the 10th-90th percentiles of the library's times
    # of finds (1.6-3.2 s; median 2.1 s): what the server's clock measured is the observer's time
    lo, hi = np.quantile(np.concatenate(red_times), [0.1, 0.9])
    assert lo <= t.loc["red", "median_time_found_s"] <= hi, (lo, t.loc["red", "median_time_found_s"], hi)
    assert (root / "report" / "table_i.md").is_file() and (root / "report" / "km.png").is_file()
    # clicks carry their position, timeouts none -- but a late click (a timeout on the server's clock, above) keeps the
    # position it was sent with, for the audit
    assert formal.loc[formal["timed_out"] & ~formal["late"], "click_x"].isna().all()
    assert formal.loc[~formal["timed_out"] | formal["late"], "click_x"].notna().all()


def test_simulate_refuses_what_is_not_loopback_or_not_a_site(tmp_path):
    for url in ("http://10.0.0.1:5000", "https://127.0.0.1:5000", "http://example.com/", "ftp://127.0.0.1/", "x"):
        with pytest.raises(CamoError):
            check_loopback(url)
    assert check_loopback("http://127.0.0.1:5000") == ("127.0.0.1", 5000)
    assert check_loopback("http://localhost:81/") == ("localhost", 81)
    import socket

    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with pytest.raises(CamoError, match="no study site answers"):
        simulate(f"http://127.0.0.1:{port}", 1, max_seconds=5)
    with pytest.raises(CamoError, match="participants"):
        simulate(f"http://127.0.0.1:{port}", 0)


def test_observer_option_parsing():
    cfg = parse_observer("display_deg=14, criterion=4,start=random")
    assert cfg.display_deg == 14.0 and cfg.criterion == 4.0 and cfg.start == "random"
    for bad in ("nokey", "bogus=1", "criterion=abc", "fixation_s=0"):
        with pytest.raises(CamoError):
            parse_observer(bad)


def test_cli_simulate_is_registered():
    from study_site.cli import register

    p = argparse.ArgumentParser(prog="camo")
    register(p.add_subparsers(dest="command", required=True))
    args = p.parse_args(["study", "simulate", "--url", "http://10.1.2.3:5000", "--participants", "3"])
    with pytest.raises(CamoError, match="loopback"):
        args.func(args)
