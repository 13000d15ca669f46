"""The vision front end on real photos: detection in the valid region only, and KLT on real
texture under known rotations (the full run: tools/bench_klt_real.py)."""

import pytest
from _tools import load_tool

klt = load_tool("bench_klt_real")

needs_photos = pytest.mark.skipif(
    not klt.PHOTOS.exists(), reason=f"real mirror photos not present ({klt.PHOTOS})"
)


@needs_photos
def test_no_feature_outside_the_mirror_annulus_on_real_photos():
    """No feature on the mirror's rim, the camera's own reflection or the black corners."""
    r = klt.detection_on_photos(klt.photos())
    print(r)
    assert r["photos"] == 18 and r["features"] > 500
    assert r["outside_valid_region"] == 0
    assert r["closest_to_region_edge_px"] >= 10.0  # half a KLT window off the edges


@needs_photos
def test_klt_on_real_texture_with_and_without_the_gyro():
    r = klt.run(frames=10, yaw_rate=45.0, wobble=3.0, photo=klt.PHOTOS / "1.jpg", seed=1)
    print(r)
    with_gyro, without = r["with_gyro"], r["without_gyro"]
    assert r["rotation_per_frame_deg"]["median"] > 5.0
    assert with_gyro["track_scores"] > 300
    assert with_gyro["error_px_median"] < 0.3 and with_gyro["error_px_p95"] < 1.0
    # without the gyro's prediction a turn of ~10° per frame loses most tracks
    assert without["track_scores"] < 0.7 * with_gyro["track_scores"]
