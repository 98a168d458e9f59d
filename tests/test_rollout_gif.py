"""The rollout GIF draws each frame where the bodies and obstacles are in that frame: solver on
the left in grey, the prediction on the right coloured by its error, the mesh lines over the
colours, the axes and colour bar the same in every frame."""

import numpy as np
import pytest
from PIL import Image

from bsms.rollouts.viz import rollout_gif

SQUARE = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
CELLS = np.array([[0, 1, 2], [0, 2, 3]])


def frames_of(path) -> np.ndarray:
    with Image.open(path) as gif:
        frames = []
        for k in range(gif.n_frames):
            gif.seek(k)
            frames.append(np.asarray(gif.convert("RGB"), dtype=np.int16))
    return np.stack(frames)


def coloured(frame: np.ndarray) -> np.ndarray:
    """Pixels that are neither white nor grey: the error colours."""
    return (frame.max(axis=-1) - frame.min(axis=-1)) > 40


def test_each_frame_draws_the_body_and_obstacle_where_they_are(tmp_path):
    steps = 4
    shift = np.array([[0.6 * k, 0.0] for k in range(steps)])[:, None]
    predicted = SQUARE[None] + shift
    truth = predicted + np.array([0.05, 0.0])  # an error that colours the prediction
    truth[0] = predicted[0]
    bar = np.array([[-0.5, -0.2], [0.5, -0.2]])  # an obstacle segment under the body, moving with it
    obstacle = bar[None] + shift
    gif = rollout_gif(CELLS, predicted, tmp_path / "moving.gif", truth=truth,
                      obstacles=(obstacle, np.array([[0, 1]])), frame_dt=0.1)
    frames = frames_of(gif)
    assert frames.shape[0] == steps
    width = frames.shape[2]
    left, right = frames[:, :, : width // 2], frames[:, :, width // 2:]
    assert not coloured(left).any(), "the solver's panel is drawn in grey"
    # the colour bar (right edge) is the same static background in every frame (up to each frame's palette)
    assert np.abs(right[:, :, -60:] - right[0, :, -60:]).max() <= 8
    body = coloured(right[:, :, : right.shape[2] - 120])  # the prediction's panel without the colour bar
    centres = [np.nonzero(f.any(axis=0))[0].mean() for f in body]
    assert np.all(np.diff(centres) > 10), f"the coloured body moves right frame by frame: {centres}"
    dark = left.max(axis=-1) < 200
    dark &= ~dark.all(axis=0)  # what moves: the solver's mesh lines and the obstacle, not the axes' frame
    columns = [np.nonzero(f.any(axis=0))[0] for f in dark]
    spans = [(c.min(), c.max()) for c in columns]
    assert all(b[0] > a[0] and b[1] > a[1] for a, b in zip(spans[:-1], spans[1:], strict=True)), spans


def test_mesh_lines_are_drawn_over_the_colours(tmp_path):
    predicted = np.stack([SQUARE, SQUARE + 0.01])
    truth = np.stack([SQUARE, SQUARE])
    gif = rollout_gif(CELLS, predicted, tmp_path / "lines.gif", truth=truth)
    last = frames_of(gif)[-1]
    right = last[:, last.shape[1] // 2: last.shape[1] - 120]
    rows, cols = np.nonzero(coloured(right))
    inside = right[rows.min() + 4: rows.max() - 4, cols.min() + 4: cols.max() - 4]  # one error: one colour
    fill = np.median(inside.reshape(-1, 3), axis=0)
    line = np.abs(inside - fill).sum(axis=-1) > 60
    diagonal = np.nonzero(line)
    assert len(diagonal[0]) > inside.shape[0] // 2, "the diagonal edge of the two cells shows over the colours"
    # on the diagonal from bottom left to top right: column grows as row falls
    assert np.corrcoef(*diagonal)[0, 1] < -0.9


def test_obstacle_frames_must_cover_the_rollout(tmp_path):
    with pytest.raises(ValueError, match=r"for each of the 3 frames drawn"):
        rollout_gif(CELLS, np.stack([SQUARE] * 3), tmp_path / "short.gif",
                    obstacles=(np.zeros((2, 2, 2)), np.array([[0, 1]])))
