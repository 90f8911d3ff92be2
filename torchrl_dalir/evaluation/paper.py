"""The paper's reported numbers, to print next to ours (``../shared/paper/dali-r.tex``, Table 1:
mean success in % over three seeds, 100 evaluation episodes per task)."""

from __future__ import annotations

TABLE1_TASKS = ("door", "pen", "disassemble", "shelf-place", "stick-pull", "pick-place-wall")

# backbone -> task -> (base policy, + DALI-R)
TABLE1 = {
    "dp": {
        "door": (50.7, 57.8),
        "pen": (46.2, 52.0),
        "disassemble": (67.7, 79.0),
        "shelf-place": (46.7, 53.3),
        "stick-pull": (49.3, 53.0),
        "pick-place-wall": (61.7, 69.3),
    },
    "fm": {
        "door": (47.2, 54.8),
        "pen": (50.8, 56.3),
        "disassemble": (76.3, 84.7),
        "shelf-place": (49.3, 56.3),
        "stick-pull": (48.7, 50.7),
        "pick-place-wall": (63.3, 71.3),
    },
}
