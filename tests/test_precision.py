import pytest
import torch

from torchrl_dalir.training import precision
from torchrl_dalir.training.policy import PolicyTrainingConfig


@pytest.mark.parametrize("native", [True, False])
def test_auto_uses_bf16_only_where_it_is_native(monkeypatch, native):
    monkeypatch.setattr(precision, "native_bf16", lambda device: native)
    assert precision.autocast_dtype("auto", "cpu") == (torch.bfloat16 if native else None)
    assert precision.autocast_dtype("fp32", "cpu") is None


def test_forcing_emulated_bf16_warns(monkeypatch):
    monkeypatch.setattr(precision, "native_bf16", lambda device: False)
    with pytest.warns(UserWarning, match="many times slower"):
        assert precision.autocast_dtype("bf16", "cpu") == torch.bfloat16
    monkeypatch.setattr(precision, "native_bf16", lambda device: True)
    assert precision.autocast_dtype("bf16", "cpu") == torch.bfloat16  # no warning where native


def test_unknown_precision_is_refused():
    with pytest.raises(ValueError, match="precision must be one of"):
        PolicyTrainingConfig(precision="fp16")
    with pytest.raises(ValueError, match="precision must be one of"):
        precision.autocast_dtype("half", "cpu")


def test_native_bf16_needs_the_bf16_instructions(monkeypatch):
    # AVX-512 alone (oneDNN's own check says yes) is emulation: only AVX512_BF16 or AMX count
    monkeypatch.setattr(torch.cpu, "_is_avx512_bf16_supported", lambda: False)
    monkeypatch.setattr(torch.cpu, "_is_amx_tile_supported", lambda: False)
    assert not precision.native_bf16("cpu")
    monkeypatch.setattr(torch.cpu, "_is_amx_tile_supported", lambda: True)
    assert precision.native_bf16("cpu")
    assert not precision.native_bf16("meta")
