"""scripts/reproduce.py --quick: every experiment runs and lands on the page with its figure."""

from __future__ import annotations

from legged_casters.tools import reproduce


def test_quick_reproduction_writes_every_experiment(tmp_path, capsys):
    assert reproduce.main(["--quick", "--out", str(tmp_path)]) == 0
    page = (tmp_path / "results.md").read_text()
    for experiment in (
        "Fig. 3",
        "Fig. 6",
        "Fig. 9",
        "Fig. 10",
        "Table II",
        "Fig. 1 / Fig. 8 slalom",
        "Table II / Fig. 11",
    ):
        assert f"| {experiment}" in page, experiment
    rows = [line for line in page.splitlines() if line.startswith("| Fig. 6 error angles")]
    seconds = float(rows[0].split("|")[3].split()[0])
    assert 0.0 < seconds < 5.0  # the posture recovers after the reversal (measured, not typed)
    for name in ("fig3_force.png", "fig6_posture.png", "fig9_top_speed.png", "fig10_modes.png", "fig8_slalom.png"):
        assert (tmp_path / "results" / name).stat().st_size > 5000
        assert f"(results/{name})" in page
    assert reproduce.main(["--only", "fig99", "--out", str(tmp_path)]) == 2
    assert "unknown" in capsys.readouterr().err
