"""The trajectory plot's top view lies in the map's gravity plane."""

from __future__ import annotations

from types import SimpleNamespace

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from planarloc.geometry.validation import InputError  # noqa: E402
from planarloc.viz.trajectory import gravity_plane_basis, plot_localization, save_localization_plot  # noqa: E402


@pytest.mark.parametrize("g, ex, ey", [((0, 1, 0), (1, 0, 0), (0, 0, 1)),      # y down (KITTI, generated worlds)
                                       ((0, 0, -1), (1, 0, 0), (0, 1, 0)),     # z up (OpenLORIS)
                                       ((-2, 0, 0), (0, 1, 0), (0, 0, 1))])   # x up
def test_the_plane_is_perpendicular_to_gravity_seen_from_above(g, ex, ey) -> None:
    bx, by, _ = gravity_plane_basis(g)
    np.testing.assert_allclose(bx, ex, atol=1e-12)
    np.testing.assert_allclose(by, ey, atol=1e-12)
    down = np.asarray(g, float) / np.linalg.norm(g)
    assert np.cross(bx, by) @ -down == pytest.approx(1.0)     # right-handed about "up": a map, not a mirror


def test_a_tilted_gravity_gives_a_tilted_plane() -> None:
    g = np.array([0.0, np.cos(0.2), np.sin(0.2)])
    ex, ey, name = gravity_plane_basis(g)
    assert name == "x" and abs(ex @ g) < 1e-12 and abs(ey @ g) < 1e-12 and abs(ex @ ey) < 1e-12
    with pytest.raises(InputError, match="g_world"):
        gravity_plane_basis([0, 0, 0])


def test_the_plot_draws_the_projection(tmp_path) -> None:
    """A z-up world: the ground truth is drawn at (x, y), whatever its height."""
    truth = [(1.0, 2.0, 5.0), (3.0, -1.0, 7.0)]
    results = [SimpleNamespace(truth_center=c, success=True, translation_error_m=0.1) for c in truth]
    fig, ax = plt.subplots()
    sc = plot_localization(ax, np.zeros((2, 3)), results, g_world=(0, 0, -1))
    np.testing.assert_allclose(sc.get_offsets(), [[1.0, 2.0], [3.0, -1.0]])
    assert "gravity plane" in ax.get_xlabel()
    plt.close(fig)
    save_localization_plot(tmp_path / "p.png", np.zeros((2, 3)), results, "t", g_world=(0, 0, -1))
    assert (tmp_path / "p.png").stat().st_size > 1000
