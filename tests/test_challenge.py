import json

from pipeline.app.challenge import confusion_text, generate, key_path, score
from pipeline.app.cli import main


def test_generate_hides_the_key_and_score_counts(tmp_path):
    out = tmp_path / "chal"
    kp = generate(3, 11, out)
    assert kp == key_path(out) and kp.exists()
    assert not kp.is_relative_to(out)
    names = sorted(p.name for p in out.iterdir())
    assert names == ["rec_000.mcap", "rec_001.mcap", "rec_002.mcap"]
    key = json.loads(kp.read_text())
    for rec in key["recordings"].values():
        for name in rec["effects"]:
            assert rec["strength_x_threshold"][name] > 0
    # nothing in the recordings names an effect
    for p in out.iterdir():
        blob = p.read_bytes()
        for word in (b"hard_iron", b"soft_iron", b"time_offset", b"eddy", b"drift", b"disturb"):
            assert word not in blob
    res_dir = tmp_path / "res"
    for p in sorted(out.glob("*.mcap")):
        assert main(["diagnose", str(p), "--out", str(res_dir / p.stem)]) == 0
        d = json.loads((res_dir / p.stem / "diagnosis.json").read_text())
        assert d["format"] == "magalign.diagnosis/1"
        cal = json.loads((res_dir / p.stem / "calibration.json").read_text())
        assert cal["format"] == "magalign.calibration/1"
    r = score(out, res_dir)
    # the score counted from the key and the diagnoses, recounted here from the files
    found = {p.stem: {f["effect"] for f in json.loads(
        (res_dir / p.stem / "diagnosis.json").read_text())["findings"]}
        for p in out.glob("*.mcap")}
    true = {name: set(rec["effects"]) for name, rec in key["recordings"].items()}
    assert r["n"] == 3
    assert r["exact"] == sum(found[n] == true[n] for n in true)
    assert [(row["recording"], set(row["true"]), set(row["found"])) for row in r["rows"]] == [
        (n, true[n], found[n]) for n in sorted(true)]
    # every true effect that was found is on the confusion table's diagonal
    for n in true:
        for e in true[n] & found[n]:
            assert r["confusion"][e][e] >= 1, (n, e, r["confusion"])
    text = confusion_text(r)
    assert "true/found" in text
    for e in set().union(*true.values()):
        assert e in text
    assert main(["score", str(out), str(res_dir)]) == 0


def test_concealed_gradient_and_sample_hold_are_found_and_nulls_stay_clean(tmp_path):
    """A gradient along a path (positions in a room frame) and a sample-and-hold sensor are
    found with their parameters within 3 sigma or 10 %; a null recording gets neither."""
    import numpy as np

    out = tmp_path / "chal"
    kp = generate(0, 5, out, only=[["field_gradient"], ["sample_hold"], []])
    key = json.loads(kp.read_text())["recordings"]
    res = tmp_path / "res"
    found = {}
    for p in sorted(out.glob("*.mcap")):
        assert main(["diagnose", str(p), "--out", str(res / p.stem)]) == 0
        d = json.loads((res / p.stem / "diagnosis.json").read_text())
        found[p.stem] = {f["effect"]: f for f in d["findings"]}
        if not key[p.stem]["effects"]:
            assert not {"field_gradient", "sample_hold"} & set(found[p.stem]), p.stem
    g = found["rec_000"].get("field_gradient")
    assert g is not None, list(found["rec_000"])
    want = np.asarray(key["rec_000"]["effects"]["field_gradient"]["G_nT_per_m"])
    M, S = np.asarray(g["params"]["G_nT_per_m"]), np.asarray(g["sigma"]["G_nT_per_m"])
    err = np.abs(M - want)
    assert np.all((err <= 3 * S) | (err <= 0.1 * np.abs(want).max())), (M, want, S)  # nT/m
    h = found["rec_001"].get("sample_hold")
    assert h is not None, list(found["rec_001"])
    true_rate = key["rec_001"]["effects"]["sample_hold"]["native_rate_hz"]
    assert abs(h["params"]["native_rate_hz"] - true_rate) <= max(
        3 * h["sigma"]["native_rate_hz"], 0.1 * true_rate)  # Hz
    true_rep = key["rec_001"]["effects"]["sample_hold"]["repeated_fraction"]
    assert abs(h["params"]["repeated_fraction"] - true_rep) < 0.01
