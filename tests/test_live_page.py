"""The live page in headless Chromium (driven by Playwright over the Debian chromium): each state
it must show is put on a scripted source and checked by the pixels of a screenshot — the phantom
visible, its colour following the load, the tracker's cage, the link outage and out-of-envelope
banners — plus orbit and zoom, the pose convention, a quadratic model's surface, nothing loaded
from elsewhere and no console error."""

from __future__ import annotations

import io
import queue
import shutil
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from softphantom.records import ChannelLayout
from softphantom.estimation import Estimate
from softphantom.estimation.stream import marker_estimate
from softphantom.pose import Pose6, matrix_from_ypr
from softphantom.sensing.sources import SourceEvent
from softphantom.viz.live import LiveConfig, LiveGeometry, LiveSession, SyntheticSource, ellipsoid_geometry

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="chromium not installed "
                                "(scripts/install-system-deps.sh installs it)")
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync"]
PAGE = "?scale=1&xray=0"  # full resolution (no adaptation), opaque surface: true colours


@pytest.fixture(scope="module")
def browser():
    from playwright.sync_api import sync_playwright

    with tempfile.TemporaryDirectory() as profile, sync_playwright() as p:
        ctx = p.chromium.launch_persistent_context(profile, executable_path=CHROMIUM, headless=True,
                                                   args=CHROMIUM_ARGS, viewport={"width": 1400, "height": 900})
        try:
            yield ctx
        finally:
            ctx.close()


class Watched:
    """A page with what it logged and requested."""

    def __init__(self, ctx, url: str):
        self.page = ctx.new_page()
        self.errors: list[str] = []
        self.requests: list[str] = []
        self.page.on("console", lambda m: self.errors.append(m.text) if m.type == "error" else None)
        self.page.on("pageerror", lambda e: self.errors.append(str(e)))
        self.page.on("request", lambda r: self.requests.append(r.url))
        self.origin = url.split("/", 3)[:3]
        self.page.goto(url)

    def state(self, expr: str):
        return self.page.evaluate(f"() => {{ const S = window.__softphantomLive; return {expr}; }}")

    def wait(self, cond: str, timeout_s: float = 20.0) -> None:
        self.page.wait_for_function(f"() => {{ const S = window.__softphantomLive; return !!S && ({cond}); }}",
                                    timeout=timeout_s * 1e3)

    def settle(self, act) -> None:
        """Do ``act``, then wait until the page has drawn since and its camera has stopped."""
        r0 = self.state("S.renders")
        act()
        self.wait(f"S.renders > {r0} && !S.moving && !S.dirty")

    def shot(self, selector: str = "#view3d") -> np.ndarray:
        from PIL import Image

        self.wait("S.renders > 0 && !S.dirty && !S.textDirty")
        # the view without the banner: a scripted source that stops sending turns the link
        # "stalled" after 1 s, which a slow machine can reach before the shot
        hide = "hidden" if selector != "#banner" else ""
        self.page.evaluate(f"document.getElementById('banner').style.visibility = '{hide}'")
        png = self.page.locator(selector).screenshot()
        self.page.evaluate("document.getElementById('banner').style.visibility = ''")
        return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=float)

    def close(self) -> None:
        own = "/".join(self.origin)
        assert all(u.startswith(own + "/") or u.startswith("data:") for u in self.requests), self.requests
        assert not self.errors, self.errors
        self.page.close()


class ScriptedSource:
    """An estimate source the test drives: :meth:`put` hands one estimate (and the surface and
    tracker pose to show with it) to the live session."""

    def __init__(self, geometry: LiveGeometry):
        self.geometry = geometry
        self.layout = geometry.layout
        self._q: queue.Queue = queue.Queue()
        self._pos = geometry.nodes.copy()
        self._tracker: list[dict] = []
        self.t = 0.0

    def put(self, est: Estimate, positions: np.ndarray | None = None, tracker: dict | None = None) -> None:
        self._q.put((est, positions, tracker))

    def estimate(self, force=(0.0, 0.0, 0.0), xyz_mm=(0.0, 0.0, 0.0), ypr_deg=(0.0, 0.0, 0.0), **kw) -> Estimate:
        self.t += 1 / 77
        return Estimate(t=self.t, force=np.asarray(force, float), p_urethra=0.0,
                        pose=Pose6(np.asarray(xyz_mm) * 1e-3, np.radians(ypr_deg)),
                        target_shift={k: np.array([0.0, 1e-3 * float(np.linalg.norm(force)), 0.0])
                                      for k in self.geometry.targets},
                        volume_pred=np.zeros(4), volume_meas=np.zeros(4), cond_W=20.0, qp_status="optimal",
                        step_time=2e-4, **{"layout": self.layout, **kw})

    def end(self) -> None:
        self._q.put(None)

    def __iter__(self):
        while (item := self._q.get()) is not None:
            est, pos, tracker = item
            if pos is not None:
                self._pos = pos
            if tracker is not None:
                self._tracker.append(tracker)
            yield est

    def node_positions(self) -> np.ndarray:
        return self._pos

    def poll_tracker(self) -> list[dict]:
        out, self._tracker = self._tracker, []
        return out


def _dent(geo: LiveGeometry, depth_m: float) -> np.ndarray:
    """The surface pushed in around p_ext (a Gaussian dent of ``depth_m`` along +y, σ 9 mm)."""
    w = np.exp(-np.sum((geo.nodes - geo.p_ext) ** 2, axis=1) / (2 * 0.009 ** 2))
    return geo.nodes + np.outer(w, [0.0, depth_m, 0.0])


def _surface(img: np.ndarray) -> np.ndarray:
    """Pixels that are not the white background."""
    return np.abs(img - 255).sum(axis=2) > 40


def _middle(img: np.ndarray) -> np.ndarray:
    h, w, _ = img.shape
    return img[h // 5:4 * h // 5, w // 5:4 * w // 5]


def _high(img: np.ndarray) -> np.ndarray:
    """Pixels in the green-yellow half of viridis (large displacement): green above blue."""
    return img[..., 1] > img[..., 2] + 30


def _show(src: ScriptedSource, page: Watched, est: Estimate, **kw) -> None:
    """Put one estimate and wait until the page has drawn it."""
    seq = page.state("S.lastSeq")
    time.sleep(0.05)  # the pump sends the surface at the view rate (30 Hz): a new one with this estimate
    src.put(est, **kw)
    page.wait(f"S.lastSeq > {seq} && !S.dirty && !S.textDirty")


@pytest.mark.slow
def test_page_states_by_pixels(browser, coarse_model, tmp_path):
    geo = LiveGeometry.from_model(coarse_model)
    src = ScriptedSource(geo)
    with LiveSession(src, LiveConfig(http_port=0, stream_port=None, view_rate_Hz=30)) as s:
        page = Watched(browser, s.url + PAGE)
        try:
            _show(src, page, src.estimate())
            page.wait("S.frames > 0 && S.status && S.status.link === 'ok'")
            rest = page.shot()
            # the phantom fills the middle of the view; at rest its colour is the low end of the map
            assert _surface(_middle(rest)).mean() > 0.3
            assert _high(_middle(rest)).mean() < 0.002
            assert page.state("S.surfaceMax") < 1e-3 and page.state("S.colorMax") == pytest.approx(0.4)  # float32 wire
            # under load: the dent is green-yellow, the colour bar spans its depth, in mm
            dented = _dent(geo, 0.006)
            _show(src, page, src.estimate(force=(0.0, 3.0, 0.0)), positions=dented)
            loaded = page.shot()
            u_mm = np.linalg.norm(dented - geo.nodes, axis=1)[np.unique(geo.faces)].max() * 1e3
            assert page.state("S.surfaceMax") == pytest.approx(u_mm, abs=1e-3)
            assert page.state("S.colorMax") == pytest.approx(6.0)  # the round number above 5.x mm
            ticks = page.page.locator("#colorbar-ticks span").all_inner_texts()
            assert ticks[0] == "6.00" and ticks[-1] == "0.00"
            assert _high(_middle(loaded)).mean() > 0.01, _high(_middle(loaded)).mean()
            assert (np.abs(loaded - rest).sum(axis=2) > 60).mean() > 0.01
            # the force arrow's label, the targets' shifts
            assert page.page.locator(".label3d.force").inner_text() == "F 3.00 N"
            assert page.page.locator(".label3d.target").all_inner_texts() == [f"{k} 3.00 mm" for k in geo.targets]
            # the tracker's pose: an orange cage appears beside the estimate
            no_tracker = loaded
            _show(src, page, src.estimate(force=(0.0, 3.0, 0.0)),
                  tracker={"x_mm": 6.0, "y_mm": 0.0, "z_mm": 4.0, "yaw_deg": 10.0, "pitch_deg": 0.0, "roll_deg": 0.0})
            tracked = page.shot()
            orange = lambda im: (im[..., 0] > 200) & (im[..., 0] - im[..., 2] > 90) & (im[..., 1] > 80) & (im[..., 1] < 200)
            assert orange(tracked).mean() > 0.002 and orange(no_tracker).mean() < 0.0005, orange(tracked).mean()
            # out of the envelope: an amber banner; then a link outage: a red one, then back to normal
            _show(src, page, src.estimate(force=(0.0, 3.0, 0.0), in_envelope=False))
            banner = page.shot("#banner")
            amber = (banner[..., 0] > 180) & (banner[..., 1] > 100) & (banner[..., 1] < 170) & (banner[..., 2] < 60)
            assert amber.mean() > 0.5 and page.page.locator("#badge-envelope").inner_text() == "OUT OF ENVELOPE"
            _show(src, page, marker_estimate(SourceEvent(src.t, "silent", "no valid frame for 0.5 s"), list(geo.targets),
                                                   src.layout))
            page.wait("S.status.link === 'outage'")
            banner = page.shot("#banner")
            red = (banner[..., 0] > 180) & (banner[..., 1] < 90) & (banner[..., 2] < 90)
            assert red.mean() > 0.5
            assert page.page.locator("#badge-link").inner_text().startswith("LINK OUTAGE: silent")
            assert page.page.locator(".label3d.force").inner_text() == "F 3.00 N"  # the last estimate stays
            _show(src, page, src.estimate())
            page.wait("S.status.link === 'ok'")
            assert page.page.locator("#banner").is_hidden()
            # orbit (drag) and zoom (wheel) move the camera
            before = page.shot()
            box = page.page.locator("#view3d canvas:not(.gizmo)").bounding_box()
            cx, cy = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
            page.page.mouse.move(cx, cy)
            page.page.mouse.down()
            page.page.mouse.move(cx + 200, cy + 40, steps=8)
            page.page.mouse.up()
            page.wait("S.renders > 0", 5)
            time.sleep(0.5)  # most of the orbit's damping (all of it takes ~4 s: S.moving)
            orbited = page.shot()
            assert (np.abs(orbited - before).sum(axis=2) > 60).mean() > 0.05
            covered = _surface(orbited).mean()
            page.page.mouse.wheel(0, -600)
            time.sleep(0.5)
            assert _surface(page.shot()).mean() > covered * 1.3
            # the pose convention: R = Rz(yaw)·Rx(pitch)·Ry(roll), as softphantom.pose has it
            m = page.state("S.poseMatrix({x_mm: 1, y_mm: 2, z_mm: 3, yaw_deg: 30, pitch_deg: -20, roll_deg: 10})")
            m = np.array(m).reshape(4, 4).T  # three.js stores columns
            np.testing.assert_allclose(m[:3, :3], matrix_from_ypr(np.radians([30, -20, 10])), atol=1e-6)
            np.testing.assert_allclose(m[:3, 3], [1, 2, 3])
            # the cavities are drawn (solid, see-through off: behind the surface), one legend row each
            assert page.state("S.cavityTriangles") == sum(len(v) for v in geo.cavities.values()) > 0
            assert page.page.locator("#legend div").count() == len(coarse_model.cavities)
            page.page.screenshot(path=str(tmp_path / "page.png"))
            shutil.copy(tmp_path / "page.png", Path(tempfile.gettempdir()) / "softphantom-live-test.png")  # a human look
            page.close()
        finally:
            src.end()


def _quadratic(model) -> SimpleNamespace:
    """The model's surfaces as 6-node triangles (VTK order: corners, then mid-edge nodes of
    (0,1), (1,2), (2,0)), each mid-edge node a new node bulged 0.3 mm outward from the bulb centre."""
    nodes = [np.asarray(model.nodes)]
    mid: dict[tuple[int, int], int] = {}

    def six(tris: np.ndarray) -> np.ndarray:
        out = []
        for a, b, c in tris:
            row = [a, b, c]
            for i, j in ((a, b), (b, c), (c, a)):
                key = (min(i, j), max(i, j))
                if key not in mid:
                    p = (model.nodes[i] + model.nodes[j]) / 2
                    mid[key] = sum(len(n) for n in nodes)
                    nodes.append((p + 3e-4 * p / np.linalg.norm(p))[None])
                row.append(mid[key])
            out.append(row)
        return np.array(out)

    outer6 = six(model.outer_faces)
    cav6 = {k: six(v) for k, v in model.cavities.items()}
    return SimpleNamespace(nodes=np.vstack(nodes), outer_faces=model.outer_faces, outer_faces6=outer6,
                           cavities=model.cavities, cavities6=cav6, targets=model.targets, p_ext=model.p_ext)


def test_quadratic_model_surface(browser, coarse_model):
    q = _quadratic(coarse_model)
    geo = LiveGeometry.from_model(q)
    # each 6-node triangle drawn as 4 through its mid-edge nodes, the same way round
    assert len(geo.faces) == 4 * len(q.outer_faces6)
    first = geo.node_index[geo.faces[:4]]
    a, b, c, ab, bc, ca = q.outer_faces6[0]
    assert first.tolist() == [[a, ab, ca], [ab, b, bc], [ca, bc, c], [ab, bc, ca]]
    n = np.cross(*(q.nodes[q.outer_faces6[0, 1:3]] - q.nodes[a]))
    for tri in q.nodes[first]:
        assert np.cross(tri[1] - tri[0], tri[2] - tri[0]) @ n > 0
    assert set(geo.cavities) == set(coarse_model.cavities)
    assert sum(map(len, geo.cavities.values())) == 4 * sum(map(len, q.cavities6.values()))
    src = ScriptedSource(geo)
    with LiveSession(src, LiveConfig(http_port=0, stream_port=None)) as s:
        page = Watched(browser, s.url + PAGE)
        try:
            _show(src, page, src.estimate(force=(0.0, 2.0, 0.0)), positions=_dent(geo, 0.004))
            img = page.shot()
            assert page.state("S.surfaceTriangles") == len(geo.faces)
            assert page.state("S.triangles") >= len(geo.faces)  # all drawn
            mid = _middle(img)
            assert _surface(mid).mean() > 0.3 and _high(mid).mean() > 0.005
            page.page.screenshot(path=str(Path(tempfile.gettempdir()) / "softphantom-live-test-p2.png"))
            page.close()
        finally:
            src.end()


def test_synthetic_source_page_plots_every_estimate(browser):
    src = SyntheticSource(rate_Hz=77, duration_s=None, period_s=10.0)  # the push peaks at t = 5 s
    with LiveSession(src, LiveConfig(http_port=0, stream_port=0)) as s:
        page = Watched(browser, s.url + "?scale=1")
        page.wait("S.latest && S.latest.t_s >= 2.5", 60)
        plot = page.shot("#plot-force")
        shown = page.state("[S.lastSeq, S.frames]")
        st = s.state.status()
        page.close()
    assert (np.ptp(plot, axis=2) > 60).mean() > 0.003  # coloured lines in the force plot
    assert st["view_dropped"] == 0 and shown[1] > 10
    assert shown[0] <= st["estimates"] - 1


def test_gizmo_click_turns_the_view(browser, coarse_model):
    """The orientation gizmo (its own canvas, drawn only when the camera turns): clicking its blue
    z axis turns the view to look along z, and the gizmo is redrawn with it."""
    geo = LiveGeometry.from_model(coarse_model)
    src = ScriptedSource(geo)
    with LiveSession(src, LiveConfig(http_port=0, stream_port=None)) as s:
        page = Watched(browser, s.url + PAGE)
        try:
            _show(src, page, src.estimate())
            gizmo = page.page.locator("#view3d canvas.gizmo")
            before, g0 = page.shot(), page.shot("#view3d canvas.gizmo")
            blue = (g0[..., 2] > 200) & (g0[..., 0] < 120) & (g0[..., 1] > 80)
            assert blue.sum() > 20, blue.sum()
            ys, xs = np.nonzero(blue)
            box = gizmo.bounding_box()
            page.settle(lambda: page.page.mouse.click(box["x"] + xs.mean(), box["y"] + ys.mean()))  # an animated turn
            after, g1 = page.shot(), page.shot("#view3d canvas.gizmo")
            assert (np.abs(after - before).sum(axis=2) > 60).mean() > 0.05
            assert (np.abs(g1 - g0).sum(axis=2) > 60).mean() > 0.05
            page.close()
        finally:
            src.end()


def test_the_end_of_a_replay_shows_ended_not_reconnecting(browser):
    """The source runs out and the session stops at once (what ``softphantom live`` does at the end
    of a replay): the page shows ``server: ended`` and keeps it (it does not try to reconnect). A
    source that says what its surface is (a replay without the estimator's field) has it shown."""
    geo = ellipsoid_geometry(subdivisions=1)
    src = ScriptedSource(geo)
    src.surface_shows = "rest shape moved rigidly by the estimated pose"  # as a replay without an atlas says
    with LiveSession(src, LiveConfig(http_port=0, stream_port=None)) as s:
        page = Watched(browser, s.url + PAGE)
        _show(src, page, src.estimate(force=(0.0, 1.0, 0.0)))
        note = page.page.locator("#surface-shows")
        assert note.is_visible() and note.inner_text() == "surface: rest shape moved rigidly by the estimated pose"
        page.wait("S.connected")
        assert page.page.locator("#badge-server").inner_text() == "server: live"
        src.end()
        assert s.wait(30)
    page.wait("!S.connected", 10)
    time.sleep(1.5)  # a reconnection attempt would have failed by now
    badge = page.page.locator("#badge-server")
    assert badge.inner_text() == "server: ended" and badge.get_attribute("data-level") == "wait"
    assert page.page.locator("#badge-link").inner_text() == "link: ended"
    page.close()  # no console error: nothing tried to reconnect


def test_a_five_arm_phantom_gets_a_cavity_and_a_plot_line_per_arm(browser):
    """A source of five named arms (here told by its geometry): the cavity plot has a measured and a
    predicted line per arm, labelled with its name and showing its value; the legend of the 3-D
    view lists each arm's cavity in its line's colour (the fifth arm's is the palette's fifth)."""
    from dataclasses import replace

    arms = ("front_zpos", "front_zneg", "back_xpos", "back_xneg", "top")
    g = ellipsoid_geometry(subdivisions=1)
    used, inv = np.unique(g.cavities["front_zpos"], return_inverse=True)  # a stand-in top cavity, 8 mm higher
    nodes = np.vstack([g.nodes, g.nodes[used] + [0.0, 0.0, 0.008]])
    cavities = {**g.cavities, "top": inv.reshape(-1, 3) + len(g.nodes)}
    geo = replace(g, nodes=nodes, node_index=np.arange(len(nodes)), cavities=cavities,
                  layout=ChannelLayout(arms, (), ("urethra",)))
    src = ScriptedSource(geo)
    with LiveSession(src, LiveConfig(http_port=0, stream_port=None)) as s:
        page = Watched(browser, s.url + PAGE)
        try:
            est = replace(src.estimate(force=(0.0, 1.0, 0.0)),
                          volume_meas=np.array([1.0, 2.0, 3.0, 4.0, 5.0]) * 1e-9, volume_pred=np.full(5, 2.5e-9))
            _show(src, page, est)
            assert page.state("S.arms") == list(arms)
            want = [n for a in arms for n in (a, f"{a} pred")]
            assert page.state('S.series["plot-cavities"]') == want
            legend = "#plot-cavities .u-legend .u-series"
            labels = page.page.eval_on_selector_all(f"{legend} .u-label", "els => els.map(e => e.textContent)")
            assert labels == ["t s", *want]
            page.page.wait_for_function(f"""() => [...document.querySelectorAll('{legend} .u-value')]
                .map(e => e.textContent).slice(1).join(' ') === '{" ".join(f"{v:.2f} 2.50" for v in range(1, 6))}'""",
                                        timeout=20e3)
            rows = page.page.eval_on_selector_all("#legend > div", "els => els.map(e => [e.textContent, "
                                                  "getComputedStyle(e.querySelector('i')).backgroundColor])")
            assert dict(rows)["top"] == "rgb(140, 86, 75)" and dict(rows)["back_xneg"] == "rgb(148, 103, 189)"
            assert dict(rows)["urethra"] == "rgb(140, 140, 140)" and len(rows) == 6
            page.close()
        finally:
            src.end()
