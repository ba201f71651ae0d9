"""``hdhil calibrate``: the torque-sensor calibration of [Taghirad97] §3 on the emulated drive.

Runs the arm-and-weight experiment of :mod:`hostsim.calibration` (wave generator
locked, known torques loaded and unloaded in both directions, at several flexspline
positions, low range and full range) on the drive of a scenario, and prints a result
in the form of [Taghirad97] Table 1: the gain (mean of the experiments' least-squares
slopes) and the consistency measure (standard deviation / mean).  Because this is an
emulator it also prints the sensor's true gain and the calibration error.

``--out FILE`` writes the result as a firmware override::

    [firmware.calibration]
    volt2Nm = 6.6229...

(TOML; JSON ``{"firmware": {"calibration": {"volt2Nm": ...}}}`` when FILE ends in
``.json``), which :func:`load_calibration` reads back as the table to merge into a
scenario's ``[firmware]`` table, so the firmware uses the calibrated gain.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from hdhil.core import jsonout
from hdhil.core.dataconf import ConfigError, from_dict
from hdhil.core.errors import UserError
from hdhil.core.files import load_json, load_toml, write_text
from hdhil.hostsim.calibration import CalibrationResult

__all__ = ["format_result", "load_calibration", "write_calibration"]

#: The calibration error the emulated experiment should stay within (README goal).
GOAL = 0.01


def _is_json(path: Path) -> bool:
    return path.suffix.lower() == ".json"


def write_calibration(
    path: str | Path, result: CalibrationResult, scenario: str = "", deferred: Any = None
) -> None:
    """Write ``{firmware: {calibration: {volt2Nm: gain}}}`` to ``path`` (JSON if it ends
    in ``.json``, TOML otherwise); ``deferred``: the
    :class:`hdhil.core.files.AtomicOutput` to write it through, renamed into place with
    the command's other outputs (:func:`hdhil.core.files.commit_outputs`)."""
    path = Path(path)
    gain = result.gain_Nm_per_V
    if _is_json(path):
        text = jsonout.dumps({"firmware": {"calibration": {"volt2Nm": gain}}}, indent=2) + "\n"
    else:
        text = (
            "# hdhil calibrate: arm-and-weight calibration of the torque sensor ([Taghirad97] §3)\n"
            f"# scenario {scenario or '-'}, seed {result.seed}, "
            f"{len(result.experiments)} experiments, "
            f"consistency {100 * result.consistency:.2f} %\n"
            "[firmware.calibration]\n"
            f"volt2Nm = {gain!r}\n"
        )
    write_text(path, text, "--out", deferred=deferred)


def load_calibration(path: str | Path) -> dict[str, Any]:
    """Read a calibration file; return the firmware override table.

    The file (TOML, or JSON if it ends in ``.json``) must hold exactly one table,
    ``[firmware.calibration]``, with keys of the firmware's calibration
    (:class:`firmware.config.Calibration`: ``volt2Nm``, ``volt2radps``, ...).  The
    return value is ``{"calibration": {...}}``, ready to deep-merge into a scenario's
    ``[firmware]`` table (``hdhil.core.dataconf.merge``).  Every mistake raises
    :class:`hdhil.cli.UserError` with a one-line message naming the file.
    """
    from hdhil.firmware.config import Calibration

    path = Path(path)
    what = "calibration file"
    data = load_json(path, what) if _is_json(path) else load_toml(path, what)
    expected = "expected only a [firmware.calibration] table"
    if not isinstance(data, dict) or set(data) != {"firmware"}:
        keys = ", ".join(sorted(data)) if isinstance(data, dict) else type(data).__name__
        raise UserError(f"{path}: {expected}, found: {keys or 'nothing'}")
    firmware = data["firmware"]
    if not isinstance(firmware, dict) or set(firmware) != {"calibration"}:
        keys = ", ".join(sorted(firmware)) if isinstance(firmware, dict) else repr(firmware)
        raise UserError(f"{path}: {expected}, found firmware: {keys or 'nothing'}")
    table = firmware["calibration"]
    if not isinstance(table, dict) or not table:
        raise UserError(f"{path}: [firmware.calibration] must be a non-empty table")
    try:
        from_dict(Calibration, table, "firmware.calibration")
    except ConfigError as exc:
        raise UserError(f"{path}: {exc}") from None
    return {"calibration": dict(table)}


def format_result(result: CalibrationResult, scenario: str = "") -> str:
    """The Table-1-like text report."""
    rig = result.rig
    lines = [
        "hdhil calibrate: arm-and-weight calibration of the torque sensor ([Taghirad97] §3)",
        f"  drive of scenario {scenario or '-'}, seed {result.seed}; wave generator locked;",
        f"  loading 0 -> +max -> 0 -> -max -> 0 in {rig.steps} weights per direction, "
        f"{rig.samples} ADC samples averaged per load",
        "",
        "  exp  pos  flexspline   beta   range  weight/step     gain      offset  residual",
        "             (deg)      (deg)   (Nm)     (kg)       (Nm/V)      (V)    (Nm rms)",
    ]
    for e in result.experiments:
        lines.append(
            f"  {e.index:>3}  {e.position:>3}  {e.flexspline_deg:>9.1f}  {e.beta_deg:>6.1f}"
            f"  {e.range_Nm:>6.1f}  {e.mass_per_step_kg:>10.3f}  {e.gain_Nm_per_V:>9.4f}"
            f"  {e.offset_V:>+9.4f}  {e.residual_rms_Nm:>8.4f}"
        )
    verdict = "within" if abs(result.error) <= GOAL else "OUTSIDE"
    lines += [
        "",
        "  Torque sensor gain    Consistency measure   ([Taghirad97] Table 1: 6.60 Nm/V, 2 %)",
        f"  {result.gain_Nm_per_V:.3f} Nm/V           {100 * result.consistency:.2f} %",
        "",
        f"  emulator's true gain {result.true_gain_Nm_per_V:.4f} Nm/V: calibration error "
        f"{100 * result.error:+.3f} % ({verdict} the {100 * GOAL:g} % goal)",
    ]
    return "\n".join(lines)
