"""`train --view`: the page follows the run without changing what the run writes; a busy port fails early."""

from __future__ import annotations

import socket

import numpy as np
import pytest

from igavatar.errors import InputError
from stages.train import TrainOptions, run_train
from stages.train_view import ViewSettings


def _weights(model) -> dict[str, np.ndarray]:
    with np.load(model / "weights.npz") as arrays:
        return {key: arrays[key] for key in arrays.files}


def test_view_leaves_the_model_unchanged(small_run, tmp_path):
    plain = run_train(TrainOptions(dataset=small_run / "dataset", out=tmp_path / "plain", preset="tiny", device="cpu"))
    viewed = run_train(TrainOptions(dataset=small_run / "dataset", out=tmp_path / "viewed", preset="tiny", device="cpu",
                                    view=ViewSettings(port=0, mesh_every=2, mesh_resolution=16)))
    assert "viewer" not in plain
    assert viewed["viewer"]["meshes"] == 3  # steps 2, 4 and 6 of 6
    a, b = _weights(tmp_path / "plain"), _weights(tmp_path / "viewed")
    assert a.keys() == b.keys()
    for key in a:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)


def test_busy_port_fails_before_training(small_run, tmp_path):
    busy = socket.socket()
    busy.bind(("127.0.0.1", 0))
    busy.listen(1)
    try:
        port = busy.getsockname()[1]
        with pytest.raises(InputError, match=f"--view-port {port}: already in use"):
            run_train(TrainOptions(dataset=small_run / "dataset", out=tmp_path / "model", preset="tiny", device="cpu",
                                   view=ViewSettings(port=port)))
    finally:
        busy.close()
    assert not (tmp_path / "model").exists() and not (tmp_path / "model.work").exists()
