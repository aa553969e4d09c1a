"""``ponytail_ros.animation``: a recorded run read back and drawn as a GIF.

The node's recorded live run (``live_run``): the chain's joint points read from the recording
are its published segment poses (the first joint on the recorded head's attachment point, the
segments as long as the recorded parameters say), and the GIF has one frame per requested
instant.
"""
import numpy as np
import pytest

pytest.importorskip('rclpy')
pytest.importorskip('matplotlib')
PIL = pytest.importorskip('PIL.Image')
pytestmark = pytest.mark.ros


def test_a_recorded_run_is_read_as_joint_points(live_run):
    from ponytail_ros.animation import load_run
    run = load_run(live_run.path)
    assert list(run.chains) == ['ponytail']
    t, pts = run.chains['ponytail']
    assert len(t) == len(pts) > 10 and np.all(np.diff(t) > 0)
    # The run rebuilds the chain with 8 segments on the way (``ros_helpers.CHANGES``).
    assert len({len(p) for p in pts}) == 2 and len(pts[-1]) == 9
    for p in pts:
        lengths = np.linalg.norm(np.diff(p, axis=0), axis=1)
        # Segments of a tick equally long (the length split equally): the joints closed.
        assert np.allclose(lengths, lengths[0], rtol=1e-6)
    assert run.head_t.size > 10 and run.head_q.shape == (run.head_t.size, 4)
    # the run was sent a NaN head pose (recorded as received, dropped by the node): not drawn
    assert any(not np.isfinite(m.pose.position.x) for m in live_run.sent)
    assert np.isfinite(run.head_p).all() and np.isfinite(run.head_q).all()


def test_the_gif_has_one_frame_per_instant(live_run, tmp_path):
    from ponytail_ros.animation import load_run, render
    run = load_run(live_run.path)
    t, _ = run.chains['ponytail']
    path = render(run, tmp_path / 'run.gif', start=float(t[0]), seconds=0.4, fps=10, size=1.5)
    with PIL.open(path) as gif:
        assert gif.n_frames == 4
        assert gif.size == (120, 120)
