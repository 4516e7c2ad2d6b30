import json

from pipeline.challenge import confusion_text, generate, key_path, score
from pipeline.cli import main


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
    assert r["n"] == 3 and 0 <= r["exact"] <= 3
    total_true = sum(max(1, len(row["true"])) for row in r["rows"])
    assert sum(sum(v.values()) for v in r["confusion"].values()) >= total_true
    assert "true/found" in confusion_text(r)
    assert main(["score", str(out), str(res_dir)]) == 0
