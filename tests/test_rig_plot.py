"""``hdhil plot`` of a rig's trace: one row per joint, named by the joint, each joint
read at its own identifiers on its bus's channel (as ``hdhil dump`` decodes it by name)
with its own truth."""

from __future__ import annotations

from pathlib import Path

import can
import numpy as np
import pytest

from hdhil.can.traces.reader import read_trace
from hdhil.can.traces.sidecar import read_metadata
from hdhil.canopen.mapping import trace_decoder
from hdhil.cli import main
from hdhil.dbc import codec
from hdhil.rig.evaluate import RecordingListener, _BusFrames, rig_recordings_from_trace


def _arm() -> None:
    pytest.importorskip("mujoco", reason="the arm extra (hdhil[arm]): rehabexos's URDF")


@pytest.fixture(scope="module")
def rig_trace(tmp_path_factory) -> Path:
    """0.3 s of rehabexos (four joints on two buses), traced."""
    _arm()
    trace = tmp_path_factory.mktemp("rigplot") / "rig.blf"
    code = main(["run", "--scenario", "rehabexos", "--duration", "0.3", "--trace", str(trace)])
    assert code == 0
    return trace


def _by_name(trace: Path) -> dict[str, list[dict[str, float]]]:
    """Every frame of ``trace`` decoded by name with the rig's databases, as ``hdhil
    dump`` decodes them: the signals of each message, in the trace's order."""
    decoder = trace_decoder(trace)
    out: dict[str, list[dict[str, float]]] = {}
    with read_trace(trace) as frames:
        for msg in frames:
            d = decoder.classify(msg)
            if d.message is not None:
                out.setdefault(d.message, []).append(d.signals)  # type: ignore[arg-type]
    return out


@pytest.mark.slow  # a rig's run and a figure of four rows
def test_each_joint_is_read_at_its_own_frames_and_truth(rig_trace):
    meta = read_metadata(rig_trace)
    joints, damage = rig_recordings_from_trace(rig_trace, meta["rig"])
    assert damage == ""
    named = _by_name(rig_trace)
    assert [j.name for j in joints] == ["J1", "J2", "J3", "J4"]
    assert [(j.bus, j.node_id) for j in joints] == [("can0", 2), ("can0", 3), ("can1", 2),
                                                    ("can1", 3)]  # fmt: skip
    for j in joints:
        rec = j.recording
        assert len(rec) >= 290, j.name
        # J3 and J1 share identifiers (node 2 on either bus) and J1, J2 share the
        # controller node: each row is the joint's own telemetry and truth.
        telemetry = [f["T_filtered"] for f in named[f"{j.name}_CTRL_TPDO1"]]
        mine = rec.column("T_filtered_tele")
        shown = mine[np.isfinite(mine)]
        assert np.allclose(shown, telemetry[-len(shown) :]), j.name
        truth = {f["T_true"] for f in named[f"{j.name}_TRUTH_TORQUE"]}
        true = rec.column("T_true")
        assert np.isfinite(true).mean() > 0.9, j.name
        assert set(true[np.isfinite(true)].tolist()) <= truth, j.name
    # the joints differ (J3 is the other actuation group): not one joint read four times
    assert len({float(np.nanmean(j.recording.column("T_true"))) for j in joints}) == 4


@pytest.mark.slow  # a rig's run and a figure of four rows
def test_the_figure_has_a_row_per_joint_headed_by_its_name(rig_trace, tmp_path, monkeypatch):
    import hdhil.commands.plot as plot

    drawn = []
    save = plot._save
    monkeypatch.setattr(
        plot, "_save", lambda fig, out, damage: drawn.append(fig) or save(fig, out, damage)
    )
    out = tmp_path / "rig.png"
    assert main(["plot", str(rig_trace), "--out", str(out)]) == 0
    assert out.stat().st_size > 0
    (fig,) = drawn
    rows = fig.subfigs
    headings = [sub._suptitle.get_text() for sub in rows]
    assert [h.split(":")[0] for h in headings] == ["joint J1", "joint J2", "joint J3", "joint J4"]
    assert "bus can1, node-ID 2" in headings[2]
    assert "4 joints on 2 buses (can0, can1)" in fig._suptitle.get_text()
    for sub in rows:  # the single-joint figure's Figs. 8-9: four panels, the close-up split
        titles = [ax.get_title() for ax in sub.axes]
        assert sum(t.startswith("Fig. 9 close-up") for t in titles) == 1
        assert sum(t.startswith("Fig. 8") for t in titles) == 2
        assert sum(t.startswith("Fig. 9: measured vs") for t in titles) == 1
        labels = [ax.get_ylabel() for ax in sub.axes]
        assert "torque (N·m)" in labels


@pytest.mark.slow  # a rig's run and a figure of four rows
def test_misalignment_in_one_joint_draws_its_figs_10_and_11(tmp_path, monkeypatch):
    import hdhil.commands.plot as plot

    _arm()
    override = tmp_path / "mis.toml"
    override.write_text("[joints.J2.plant.ripple]\nmisalignment_pp_Nm = 2.0\n")
    trace = tmp_path / "mis.blf"
    assert main(["run", "--scenario", "rehabexos", "--duration", "0.2", "--override",
                 str(override), "--trace", str(trace)]) == 0  # fmt: skip
    drawn = []
    monkeypatch.setattr(plot, "_save", lambda fig, out, damage: drawn.append(fig) or 0)
    assert main(["plot", str(trace), "--out", str(tmp_path / "m.png")]) == 0
    (fig,) = drawn
    with_10 = [
        sub._suptitle.get_text().split(":")[0]
        for sub in fig.subfigs
        if any(ax.get_title().startswith("Fig. 10") for ax in sub.axes)
    ]
    assert with_10 == ["joint J2"]


@pytest.mark.slow  # a rig's run and a figure of four rows
def test_what_a_rig_trace_is_not_drawn_with_is_one_line(rig_trace, tmp_path, capsys):
    out = tmp_path / "x.png"
    for args, words in (
        (["--figure", "fig8"], "--figure fig8 draws one joint's"),
        (["--scenario", "free-motion"], "scenario free-motion is a single joint"),
        (["--scenario", "arm7"], "joint J1 of the trace is not a joint of scenario arm7"),
    ):
        capsys.readouterr()
        assert main(["plot", str(rig_trace), "--out", str(out), *args]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and words in err, (args, err)
    assert not out.exists()


def test_a_sample_takes_the_truth_stamped_before_its_buss_sync():
    """A drive's truth of a sample is stamped before its bus's SYNC of that sample. On a
    loaded bus the SYNC comes late, and the next sample's truth is stamped between it
    and the sensor frame answering it, which must not take that one."""
    truth = codec("truth", "TRUTH_TORQUE")
    sensor = codec("control", "DRIVE_TPDO1")
    raw = sensor.encode_named(ADC_torque=100, ADC_tacho=0, ADC_current=0, ENC_count=0)
    frames = [
        can.Message(timestamp=(k + 0.941) * 1e-3, arbitration_id=truth.frame_id,
                    is_extended_id=True, channel=1,
                    data=truth.encode_named(T_true=float(k), T_ripple=0.0))
        for k in range(4)
    ]  # fmt: skip
    for sync_ms in (0.999, 2.849, 3.849):  # the second and third SYNC 0.85 ms late
        frames += [
            can.Message(timestamp=sync_ms * 1e-3, arbitration_id=0x080, channel=0, data=b"",
                        is_extended_id=False),
            can.Message(timestamp=(sync_ms + 0.2) * 1e-3, arbitration_id=sensor.frame_id,
                        is_extended_id=False, channel=0, data=raw),
        ]  # fmt: skip
    frames.sort(key=lambda m: m.timestamp)
    bus = _BusFrames()
    bus.listeners.append(lis := RecordingListener(1e-3))
    for msg in frames:
        (bus.on_truth if msg.channel == 1 else bus.on_frame)(msg)
    assert lis.recording.column("T_true").tolist() == [0.0, 1.0, 2.0]
