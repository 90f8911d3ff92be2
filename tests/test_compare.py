import pytest

from torchrl_dalir.evaluation.compare import paired_sign_test


def test_paired_sign_test_counts_discordant_episodes_and_gives_the_exact_binomial_p_value():
    base = [True] * 10 + [False] * 3 + [True] * 7 + [False] * 30
    dalir = [False] * 10 + [True] * 3 + [True] * 7 + [False] * 30
    result = paired_sign_test(base, dalir)
    assert (result["base_only"], result["dalir_only"]) == (10, 3)
    # 2 * P(X <= 3), X ~ Binomial(13, 1/2) = 2 * (1 + 13 + 78 + 286) / 8192
    assert result["p_value"] == pytest.approx(756 / 8192)
    assert paired_sign_test(dalir, base)["p_value"] == result["p_value"]
    assert paired_sign_test([True, False], [True, False]) == {"base_only": 0, "dalir_only": 0, "p_value": 1.0}
    assert paired_sign_test([True, False, True], [False, True, True])["p_value"] == 1.0


def test_paired_sign_test_refuses_unpaired_results():
    with pytest.raises(ValueError, match="same episodes"):
        paired_sign_test([True, False], [True])
