"""Error messages that said too little or the wrong thing (issue 38, "smaller")."""

from __future__ import annotations

import pytest
import torch

from genesis_rl.core.errors import UserInputError
from genesis_rl.sut.perception.detector import DEFAULT_WEIGHTS, VehicleDetector, load_checkpoint


def test_wrong_shape_weights_name_the_mismatched_tensor(tmp_path) -> None:
    ckpt = load_checkpoint(DEFAULT_WEIGHTS)
    first = next(iter(ckpt["state_dict"]))
    ckpt["state_dict"][first] = torch.zeros(3, 3)
    path = tmp_path / "wrong_shape.pt"
    torch.save(ckpt, path)
    with pytest.raises(UserInputError) as err:
        VehicleDetector(path)
    message = str(err.value)
    assert "\n" not in message
    assert f"size mismatch for {first}" in message and "torch.Size([3, 3])" in message
