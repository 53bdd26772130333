"""The phantom in Foxglove (softphantom.stream.foxglove): the recording's well-known messages,
decoded with the schemas foxglove-sdk ships, and the live WebSocket server read by a client."""

from __future__ import annotations

import json
import socket
import time

import numpy as np
import pytest

pytest.importorskip("foxglove", reason="foxglove-sdk (PyPI) is not installed")
protobuf = pytest.importorskip("google.protobuf", reason="protobuf (the test extra) is not installed")

import foxglove.messages as fm  # noqa: E402
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory  # noqa: E402
from mcap.reader import make_reader  # noqa: E402

from softphantom.cli import main  # noqa: E402
from softphantom.errors import UserError  # noqa: E402
from softphantom.pose.rotations import matrix_from_quat, matrix_from_ypr  # noqa: E402
from softphantom.stream import read_recording  # noqa: E402
from softphantom.stream.foxglove import (  # noqa: E402
    ARROW_MM_PER_N, FRAME_ESTIMATE, FRAME_PHANTOM, FRAME_TRACKER, TOPIC_FG_OVERLAY, TOPIC_FG_SURFACE, TOPIC_FG_TF,
    FoxgloveScene, FoxgloveServer, nice_colour_max_mm, viridis,
)
from softphantom.viz.live import LiveConfig, LiveSession  # noqa: E402
from softphantom.viz.live.source import SyntheticSource, decode_positions_mm  # noqa: E402

SDK_SCHEMAS = {"foxglove.SceneUpdate": fm.SceneUpdate.get_schema(),
               "foxglove.FrameTransforms": fm.FrameTransforms.get_schema()}


def _message_class(schema_data: bytes, name: str):
    """The protobuf class of ``name`` from a FileDescriptorSet (the schema an MCAP channel carries)."""
    pool = descriptor_pool.DescriptorPool()
    todo = list(descriptor_pb2.FileDescriptorSet.FromString(schema_data).file)
    while todo:  # dependencies first, whatever order the set lists them in
        f = todo.pop(0)
        try:
            pool.Add(f)
        except TypeError:
            todo.append(f)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(name))


def _read_foxglove(path) -> dict[str, list]:
    """Topic → decoded messages of every protobuf channel, each checked to carry the SDK's schema."""
    out: dict[str, list] = {}
    classes: dict[int, object] = {}
    with open(path, "rb") as fh:
        for schema, channel, message in make_reader(fh).iter_messages():
            if channel.message_encoding != "protobuf":
                continue
            assert schema.encoding == "protobuf" and schema.name in SDK_SCHEMAS
            assert schema.data == bytes(SDK_SCHEMAS[schema.name].data)  # the schema shipped in the SDK
            cls = classes.setdefault(schema.id, _message_class(schema.data, schema.name))
            m = cls.FromString(message.data)
            assert message.log_time == m.entities[0].timestamp.seconds * 10**9 + m.entities[0].timestamp.nanos \
                if schema.name == "foxglove.SceneUpdate" else \
                message.log_time == m.transforms[0].timestamp.seconds * 10**9 + m.transforms[0].timestamp.nanos
            out.setdefault(channel.topic, []).append(m)
    return out


def _xyz(p) -> np.ndarray:
    return np.array([p.x, p.y, p.z])


def _rotate(q, v) -> np.ndarray:
    return matrix_from_quat(np.array([q.x, q.y, q.z, q.w])) @ np.asarray(v, float)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    path = tmp_path_factory.mktemp("fg") / "s.mcap"
    src = SyntheticSource(rate_Hz=100, duration_s=0.6, subdivisions=1)
    with LiveSession(src, LiveConfig(http_port=0, stream_port=None, record=path)) as s:
        assert s.wait(timeout_s=60.0)
    return path, read_recording(path), _read_foxglove(path)


def test_recording_carries_the_scene_as_foxglove_messages(recorded):
    _path, rec, fg = recorded
    geo = rec.geometry
    assert rec.complete and rec.estimates and rec.surface and not rec.other  # the JSON channels are kept
    assert set(fg) == {TOPIC_FG_SURFACE, TOPIC_FG_OVERLAY, TOPIC_FG_TF}
    assert len(fg[TOPIC_FG_TF]) == len(fg[TOPIC_FG_OVERLAY]) == len(rec.estimates)  # one of each per estimate
    assert 1 <= len(fg[TOPIC_FG_SURFACE]) <= len(rec.surface) + 1

    rest = np.asarray(geo["nodes_mm"]) * 1e-3
    outer = np.unique(geo["faces"])
    u_seen = 0.0
    for su in fg[TOPIC_FG_SURFACE]:
        ents = {e.id: e for e in su.entities}
        assert set(ents) == {"surface", "cavities"} and all(e.frame_id == FRAME_PHANTOM for e in ents.values())
        (tri,) = ents["surface"].triangles
        assert len(tri.indices) == 3 * len(geo["faces"])  # the whole outer surface, one triangle each
        assert len(tri.points) == len(tri.colors) == len(outer) and max(tri.indices) == len(outer) - 1
        rgba = np.array([[c.r, c.g, c.b, c.a] for c in tri.colors])
        assert np.all((rgba >= 0) & (rgba <= 1)) and np.allclose(rgba[:, 3], 0.55, atol=1 / 255)
        # coloured by |u|: the colour of each vertex is viridis(|u| / the scale's top)
        pts = np.array([_xyz(p) for p in tri.points])
        u_mm = np.linalg.norm(pts - rest[outer], axis=1) * 1e3
        top = float(dict((kv.key, kv.value) for kv in ents["surface"].metadata)["colour_max_mm"])
        assert top == nice_colour_max_mm(u_mm.max()) and top >= u_mm.max()
        assert np.abs(rgba[:, :3] - viridis(u_mm / top)).max() <= 1 / 255
        u_seen = max(u_seen, u_mm.max())
        cav = ents["cavities"].triangles
        assert [len(t.indices) // 3 for t in cav] == [len(f) for f in geo["cavities"].values()]
    assert u_seen > 0.05  # the synthetic source deforms the surface
    # a Foxglove surface sent with a recorded /live/surface is that surface (same nodes, float32 mm);
    # the others go out at the view's rate, between the recorded ones (which ones: the timing's)
    recorded_mm = [decode_positions_mm(s["positions_mm_f32_b64"])[outer] for s in rec.surface]
    sent_mm = [np.array([_xyz(p) for p in su.entities[0].triangles[0].points]) for su in fg[TOPIC_FG_SURFACE]]
    assert any(np.abs(r - s).max() < 1e-6 for r in recorded_mm for s in sent_mm)


def test_recorded_force_targets_and_pose_match_the_estimates(recorded):
    _path, rec, fg = recorded
    geo = rec.geometry
    arrows = 0
    for msg, ov, tfs in zip(rec.estimates, fg[TOPIC_FG_OVERLAY], fg[TOPIC_FG_TF]):
        (tf,) = tfs.transforms
        assert (tf.parent_frame_id, tf.child_frame_id) == (FRAME_PHANTOM, FRAME_ESTIMATE)
        assert np.allclose(_xyz(tf.translation) * 1e3, [msg["x_mm"], msg["y_mm"], msg["z_mm"]])
        R = matrix_from_ypr(np.radians([msg["yaw_deg"], msg["pitch_deg"], msg["roll_deg"]]))
        assert np.allclose(matrix_from_quat(np.array([tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w])),
                           R, atol=1e-12)
        ents = {e.id: e for e in ov.entities}
        F = np.array([msg["force_x_N"], msg["force_y_N"], msg["force_z_N"]])
        if np.linalg.norm(F) <= 1e-3:  # no force: no arrow (as the page)
            assert not ents["force"].arrows
            continue
        arrows += 1
        (arrow,) = ents["force"].arrows
        L = arrow.shaft_length + arrow.head_length
        assert L == pytest.approx(min(60, max(12, ARROW_MM_PER_N * np.linalg.norm(F))) * 1e-3)
        d = _rotate(arrow.pose.orientation, [1, 0, 0])  # an arrow points along its pose's +x
        assert np.allclose(d, F / np.linalg.norm(F), atol=1e-9)
        tip = _xyz(arrow.pose.position) + L * d  # ends on the contact point, drawn as a sphere
        assert np.allclose(tip, _xyz(ents["force"].spheres[0].pose.position), atol=1e-9)
        names = list(geo["targets_mm"])
        sph = ents["targets"].spheres
        assert len(sph) == 2 * len(names) and len(ents["targets"].lines[0].points) == 2 * len(names)
        for k, name in enumerate(names):
            shift = np.array([msg[f"{name}_d{a}_mm"] for a in "xyz"])
            assert np.allclose(_xyz(sph[2 * k].pose.position) * 1e3, geo["targets_mm"][name], atol=1e-9)
            assert np.allclose(_xyz(sph[2 * k + 1].pose.position) * 1e3, np.asarray(geo["targets_mm"][name]) + shift,
                               atol=1e-9)
    assert arrows > len(rec.estimates) // 2


def test_tracker_pose_is_a_frame_with_the_rest_body_in_it_and_markers_leave_the_scene_alone():
    from softphantom.viz.live.source import ellipsoid_geometry

    geo = ellipsoid_geometry(subdivisions=1)
    scene = FoxgloveScene(geo.to_json())
    cls = _message_class(bytes(SDK_SCHEMAS["foxglove.FrameTransforms"].data), "foxglove.FrameTransforms")
    assert scene.tracker({"x_mm": 1.0, "y_mm": float("nan"), "z_mm": 0, "yaw_deg": 0, "pitch_deg": 0,
                          "roll_deg": 0, "valid": False}) == []  # a lost frame
    (m,) = scene.tracker({"x_mm": 1.0, "y_mm": 2.0, "z_mm": 3.0, "yaw_deg": 90.0, "pitch_deg": 0.0, "roll_deg": 0.0,
                          "valid": True}, t_ns=5)
    (tf,) = cls.FromString(m.data).transforms
    assert tf.child_frame_id == FRAME_TRACKER and np.allclose(_xyz(tf.translation), [1e-3, 2e-3, 3e-3])
    assert np.allclose(_rotate(tf.rotation, [1, 0, 0]), [0, 1, 0])  # yaw 90°: x → y
    su = _message_class(bytes(SDK_SCHEMAS["foxglove.SceneUpdate"].data), "foxglove.SceneUpdate")
    ents = {e.id: e for e in su.FromString(scene.surface(geo.nodes).data).entities}
    assert ents["tracker_body"].frame_id == FRAME_TRACKER and ents["tracker_body"].frame_locked
    assert len(ents["tracker_body"].triangles[0].indices) == 3 * len(geo.faces)
    marker = {"t_pub_unix_s": 1.0, "status": "event:silent: no sample", "force_x_N": None, "force_y_N": None,
              "force_z_N": None, "x_mm": None, "y_mm": None, "z_mm": None, "yaw_deg": None, "pitch_deg": None,
              "roll_deg": None}
    assert scene.estimate(marker) == []


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_live_foxglove_server_sends_every_channel_to_a_websocket_client():
    ws = pytest.importorskip("websockets.sync.client", reason="websockets (the test extra) is not installed")
    src = SyntheticSource(rate_Hz=100, duration_s=20.0, subdivisions=1)
    with LiveSession(src, LiveConfig(http_port=0, stream_port=None, foxglove_port=0)) as s:
        url = s.foxglove_url
        assert url.startswith("ws://127.0.0.1:")  # on --listen-host: loopback by default
        with ws.connect(url, subprotocols=["foxglove.sdk.v1", "foxglove.websocket.v1"], open_timeout=10) as c:
            channels: dict[int, dict] = {}
            got: dict[str, object] = {}
            deadline = time.monotonic() + 15.0
            while time.monotonic() < deadline and (len(channels) < 4 or len(got) < len(channels)):
                frame = c.recv(timeout=5.0)
                if isinstance(frame, str):
                    op = json.loads(frame)
                    if op["op"] == "advertise":
                        new = {ch["id"]: ch for ch in op["channels"]}
                        channels.update(new)
                        c.send(json.dumps({"op": "subscribe", "subscriptions": [
                            {"id": cid, "channelId": cid} for cid in new]}))
                    continue
                assert frame[0] == 1  # message data: opcode, subscription id, log time, payload
                sub = int.from_bytes(frame[1:5], "little")
                ch = channels[sub]
                if ch["encoding"] == "protobuf":
                    data = bytes(__import__("base64").b64decode(ch["schema"]))
                    assert data == bytes(SDK_SCHEMAS[ch["schemaName"]].data)
                    got[ch["topic"]] = _message_class(data, ch["schemaName"]).FromString(frame[13:])
                else:
                    got[ch["topic"]] = json.loads(frame[13:])
    assert set(got) == {TOPIC_FG_SURFACE, TOPIC_FG_OVERLAY, TOPIC_FG_TF, "/estimate"}
    assert got[TOPIC_FG_TF].transforms[0].child_frame_id == FRAME_ESTIMATE
    assert {e.id for e in got[TOPIC_FG_SURFACE].entities} == {"surface", "cavities"}
    assert {e.id for e in got[TOPIC_FG_OVERLAY].entities} == {"force", "targets"}
    assert "force_y_N" in got["/estimate"]


def test_a_foxglove_port_in_use_is_one_line_and_exit_2(capsys):
    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        port = held.getsockname()[1]
        with pytest.raises(UserError, match="in use"):
            FoxgloveServer("127.0.0.1", port)
        assert main(["live", "--duration-s", "1", "--http-port", "0", "--stream-port", "0", "--foxglove",
                     "--foxglove-port", str(port)]) == 2
    err = capsys.readouterr().err.strip()
    assert f"127.0.0.1:{port}" in err and "in use" in err and "\n" not in err and "Traceback" not in err
    assert main(["live", "--foxglove", "--foxglove-port", "70000"]) == 2
    assert "--foxglove-port" in capsys.readouterr().err
    # beyond loopback: refused without --allow-remote, as the page is
    assert main(["live", "--foxglove", "--listen-host", "0.0.0.0", "--foxglove-port", str(_free_port())]) == 2
    assert "--allow-remote" in capsys.readouterr().err
