"""Middlebury .flo files, flow metrics and the colour-wheel visualisation."""

import numpy as np
import pytest

from jaxtrack.io import flow_errors, flow_to_colour, known_flow_mask, read_flo, write_flo

MIDDLEBURY = ["Dimetrodon", "Grove2", "Grove3", "Hydrangea", "RubberWhale", "Urban2", "Urban3", "Venus"]


def test_round_trip_and_errors(tmp_path):
    flow = np.random.default_rng(0).normal(size=(7, 5, 2)).astype(np.float32)
    write_flo(tmp_path / "a.flo", flow)
    np.testing.assert_array_equal(read_flo(tmp_path / "a.flo"), flow)
    (tmp_path / "bad.flo").write_bytes(b"JUNK" + b"\0" * 8)  # the real magic is b"PIEH"
    with pytest.raises(ValueError, match="not a .flo"):
        read_flo(tmp_path / "bad.flo")
    (tmp_path / "short.flo").write_bytes(np.array([202021.25], "<f4").tobytes() + np.array([4, 4], "<i4").tobytes())
    with pytest.raises(ValueError, match="header says 4x4"):
        read_flo(tmp_path / "short.flo")
    with pytest.raises(FileNotFoundError):
        read_flo(tmp_path / "none.flo")
    with pytest.raises(ValueError, match="shape"):
        write_flo(tmp_path / "x.flo", np.zeros((3, 3)))


def test_metrics():
    gt = np.zeros((4, 4, 2))
    gt[..., 0] = 1.0
    est = gt.copy()
    est[..., 1] = 1.0
    e = flow_errors(est, gt)
    assert e["epe"] == pytest.approx(1.0) and e["pixels"] == 16
    # AAE of (1, 1, 1) vs (1, 0, 1): arccos(2 / sqrt(3 * 2)).
    assert e["aae"] == pytest.approx(np.degrees(np.arccos(2 / np.sqrt(6))))
    gt[0, 0] = 1e10
    assert flow_errors(est, gt)["pixels"] == 15


def test_colour_wheel_directions():
    flow = np.array([[[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, 0.0], [1e10, 0]]])
    img = flow_to_colour(flow, max_flow=1.0)
    assert img.shape == (1, 5, 3) and img.dtype == np.uint8
    assert (img[0, 3] == 255).all()  # zero flow is white
    assert (img[0, 4] == 0).all()  # unknown flow is black
    assert len({tuple(c) for c in img[0, :3]}) == 3  # different directions, different hues


def test_reads_the_middlebury_and_yosemite_ground_truth(shared_data):
    for name in MIDDLEBURY:
        gt = read_flo(shared_data / "flow" / name / "flow10.flo")
        assert gt.ndim == 3 and gt.shape[2] == 2
        known = known_flow_mask(gt)
        assert 0.5 < known.mean() <= 1.0
        assert np.abs(gt[known]).max() < 50
        if name in ("Dimetrodon", "Hydrangea", "RubberWhale"):
            assert not known.all()  # these mark unknown flow (DATA README)
    yos = read_flo(shared_data / "flow" / "Yosemite" / "correct_yos.flo")
    assert yos.shape == (252, 316, 2)


def test_truncated_files_bad_paths_and_degenerate_metrics(tmp_path):
    flow = np.ones((3, 4, 2), np.float32)
    path = write_flo(tmp_path / "new" / "a.flo", flow)  # missing parent folders are created
    data = path.read_bytes()
    (tmp_path / "cut.flo").write_bytes(data[:-5])
    with pytest.raises(ValueError, match="cut.flo: header says 4x3 \\(108 bytes\\), file has 103 bytes"):
        read_flo(tmp_path / "cut.flo")
    (tmp_path / "tiny.flo").write_bytes(data[:6])
    with pytest.raises(ValueError, match="tiny.flo: too short"):
        read_flo(tmp_path / "tiny.flo")
    with pytest.raises(ValueError, match="write_flo: path: .* is a folder"):
        write_flo(tmp_path / "new", flow)
    with pytest.raises(ValueError, match="write_flo: flow must have shape"):
        write_flo(tmp_path / "e.flo", np.zeros((0, 4, 2)))
    unknown = np.full((3, 4, 2), 2e9)
    with pytest.raises(ValueError, match="no pixel has known ground truth"):
        flow_errors(flow, unknown)
    with pytest.raises(ValueError, match="mask must have shape \\(3, 4\\)"):
        flow_errors(flow, flow, mask=np.ones((4, 3), bool))
    with pytest.raises(ValueError, match="max_flow must be a finite number > 0"):
        flow_to_colour(flow, max_flow=0.0)
    with pytest.raises(ValueError, match="flow_to_colour: flow must have shape"):
        flow_to_colour(flow[..., 0])
