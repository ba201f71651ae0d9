"""The firmware parameters in the controller's object dictionary, and their live update.

Objects 0x2400-0x2430 of ``dbc/controller.eds`` hold the firmware parameters
(:data:`PARAMETERS`); the scenario's configuration is written into them when the node is
built, so an SDO upload returns what runs (REAL32: to float32 precision, and the firmware
then runs with the value the OD holds).  A download passes the checks of
:class:`hdhil.canopen.services.CanopenServices` and then :class:`LiveParameters`': the new
:class:`hdhil.firmware.config.FirmwareConfig` must build (``dataclasses.replace``;
0x06090030 otherwise), and ``q_i`` of a harmonic that is not configured aborts with
0x08000022.  An aborted write changes nothing.  Accepted writes wait in ``pending`` until
the node's next cycle boundary, where :func:`apply_config` swaps the changed stages in.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from hdhil.canopen.services import ABORT_DEVICE_STATE, ABORT_INVALID_VALUE, CanopenServices
from hdhil.firmware.config import FirmwareConfig, Law, Wave, paper_config, recommended_config
from hdhil.firmware.isr import InterruptHandler, TorqueControl, TorqueFilterChain
from hdhil.firmware.stages import ReferenceGenerator

__all__ = ["PARAMETERS", "LiveParameters", "Parameter", "apply_config"]


class NotApplicable(Exception):
    """The object exists but means nothing in the running configuration (abort 0x08000022)."""


@dataclass(frozen=True)
class Parameter:
    """One firmware parameter in the controller's OD (``index:sub``) and how it maps to
    :class:`FirmwareConfig`: ``get`` reads it, ``put`` returns a config with the new
    value (None: read-only).  ``stage`` says what must be rebuilt when it changes."""

    index: int
    sub: int
    name: str
    get: Callable[[FirmwareConfig], Any]
    put: Callable[[FirmwareConfig, Any], FirmwareConfig] | None
    stage: str


_replace = dataclasses.replace


def _reference(sub: int, name: str, convert: Callable[[Any], Any] = float) -> Parameter:
    return Parameter(
        0x2400,
        sub,
        name,
        lambda c: getattr(c.reference, name),
        lambda c, v: _replace(c, reference=_replace(c.reference, **{name: convert(v)})),
        "reference",
    )


def _set_mode(c: FirmwareConfig, v: int) -> FirmwareConfig:
    return paper_config(c) if v == 0 else recommended_config(c)


def _ripple(name: str) -> Parameter:
    sub = {"r": 2, "residual_q": 3}[name]
    return Parameter(
        0x2410,
        sub,
        name,
        lambda c: getattr(c.ripple, name),
        lambda c, v: _replace(c, ripple=_replace(c.ripple, **{name: float(v)})),
        "filter",
    )


def _harmonic_q(i: int) -> Parameter:
    def get(c: FirmwareConfig) -> float:
        osc = c.ripple.oscillators
        return float(osc[i].q) if i < len(osc) else 0.0  # type: ignore[arg-type]

    def put(c: FirmwareConfig, v: float) -> FirmwareConfig:
        osc = list(c.ripple.oscillators)
        if i >= len(osc):
            raise NotApplicable
        osc[i] = _replace(osc[i], q=float(v))
        return _replace(c, ripple=_replace(c.ripple, oscillators=tuple(osc)))

    return Parameter(0x2410, 5 + i, f"q_{i + 1}", get, put, "filter")


def _desired(sub: int, name: str) -> Parameter:
    return Parameter(
        0x2420,
        sub,
        f"desired_{name}",
        lambda c: getattr(c.control.desired, name),
        lambda c, v: _replace(
            c, control=_replace(c.control, desired=_replace(c.control.desired, **{name: float(v)}))
        ),
        "desired",
    )


def _calibration(sub: int, name: str) -> Parameter:
    return Parameter(
        0x2430,
        sub,
        name,
        lambda c: getattr(c.calibration, name),
        lambda c, v: _replace(c, calibration=_replace(c.calibration, **{name: float(v)})),
        "calibration",
    )


#: The firmware parameters in the controller's OD (``dbc/controller.eds``), in OD order.
PARAMETERS: tuple[Parameter, ...] = (
    _reference(1, "wave", Wave),
    _reference(2, "bias_V"),
    _reference(3, "amplitude_V"),
    _reference(4, "frequency_Hz"),
    _reference(5, "duty"),
    _reference(6, "step_time_s"),
    _reference(7, "chirp_end_Hz"),
    _reference(8, "chirp_duration_s"),
    Parameter(
        0x2401,
        1,
        "num_samples",
        lambda c: c.num_samples,
        lambda c, v: _replace(c, num_samples=int(v)),
        "run",
    ),
    Parameter(0x2401, 2, "sample_period_s", lambda c: c.sample_period_s, None, "run"),
    Parameter(
        0x2410,
        1,
        "mode",
        lambda c: 0 if c.ripple.mode == "paper" else 1,
        _set_mode,
        "filter",
    ),
    _ripple("r"),
    _ripple("residual_q"),
    Parameter(0x2410, 4, "harmonics", lambda c: len(c.ripple.oscillators), None, "filter"),
    *(_harmonic_q(i) for i in range(4)),
    Parameter(
        0x2420,
        1,
        "law",
        lambda c: int(c.control.law),
        lambda c, v: _replace(c, control=_replace(c.control, law=Law(v))),
        "control",
    ),
    _desired(2, "amplitude_Nm"),
    _desired(3, "frequency_Hz"),
    _calibration(1, "volt2Nm"),
    _calibration(2, "volt2radps"),
)


def store_value(services: CanopenServices, index: int, sub: int, value: Any) -> None:
    """Write an OD value as the application (no SDO checks, no callbacks)."""
    var = services.od[index]
    if sub or not hasattr(var, "encode_raw"):
        var = var[sub]
    services.node.data_store.setdefault(index, {})[sub] = var.encode_raw(value)


class LiveParameters:
    """The parameter objects of one controller: written from a configuration, checked
    and staged on SDO writes.

    ``current()`` returns the configuration that runs; an accepted write leaves the new
    configuration in ``pending`` (the node applies it at its next cycle boundary and
    clears it).  ``on_accepted(parameter)`` runs after each accepted write.
    """

    def __init__(
        self,
        services: CanopenServices,
        current: Callable[[], FirmwareConfig],
        on_accepted: Callable[[Parameter], None],
    ) -> None:
        self.services = services
        self.current = current
        self.on_accepted = on_accepted
        self.pending: FirmwareConfig | None = None
        #: False when the controller runs an interrupt handler other than the firmware's
        #: own: there are no stages to retune, every write is refused (0x08000022).
        self.enabled = True
        #: A control law designed while its write was checked, kept for the swap.
        self.prebuilt_control: tuple[Any, TorqueControl] | None = None
        self._staged: tuple[int, int, Any, FirmwareConfig] | None = None
        for p in PARAMETERS:
            if p.put is None:
                continue
            services.add_validator(p.index, p.sub, self._validator(p))
            services.on_write(p.index, p.sub, self._writer(p))

    def store(self, cfg: FirmwareConfig) -> None:
        """Every parameter object to ``cfg``'s value."""
        for p in PARAMETERS:
            store_value(self.services, p.index, p.sub, p.get(cfg))

    def take_pending(self) -> FirmwareConfig | None:
        new, self.pending = self.pending, None
        return new

    def _base(self) -> FirmwareConfig:
        return self.pending or self.current()

    def _validator(self, p: Parameter) -> Callable[[Any], int | None]:
        def validate(value: Any) -> int | None:
            base = self._base()
            assert p.put is not None
            try:
                candidate = p.put(base, value)
                self._check_buildable(base, candidate)
            except NotApplicable:
                return ABORT_DEVICE_STATE
            except (ValueError, ArithmeticError, TypeError):
                return ABORT_INVALID_VALUE
            self._staged = (p.index, p.sub, value, candidate)
            return None

        return validate

    def _writer(self, p: Parameter) -> Callable[[Any], None]:
        def write(value: Any) -> None:
            staged = self._staged
            self._staged = None
            if staged is None or staged[:3] != (p.index, p.sub, value):  # pragma: no cover
                assert p.put is not None
                staged = (p.index, p.sub, value, p.put(self._base(), value))
            candidate = staged[3]
            self.pending = candidate
            self.on_accepted(p)
            if p.stage == "filter":  # mode writes change r/q: the OD follows at once
                self.store(candidate)

        return write

    def _check_buildable(self, base: FirmwareConfig, new: FirmwareConfig) -> None:
        """Raise if the stages of ``new`` that differ from ``base`` cannot be built.

        The LQG design (seconds of linear algebra at worst) is built here once and kept
        for the cycle boundary, so a design that fails aborts the SDO write instead."""
        if not self.enabled:
            raise NotApplicable
        Ts = new.sample_period_s
        if new.reference != base.reference:
            ReferenceGenerator(new.reference, Ts)
        if new.control.desired != base.control.desired:
            ReferenceGenerator(new.control.desired.reference(), Ts)
        if new.control.law != base.control.law and new.control.active:
            self.prebuilt_control = (new.control, TorqueControl(new))


@dataclass
class Applied:
    """What :func:`apply_config` rebuilt."""

    filter_restarted: bool = False
    control_rebuilt: bool = False
    control_changed: bool = False


def apply_config(
    isr: InterruptHandler,
    old: FirmwareConfig,
    new: FirmwareConfig,
    prebuilt: tuple[Any, TorqueControl] | None,
) -> Applied:
    """Swap the stages of ``isr`` that differ between ``old`` and ``new``.

    - reference generator: rebuilt; the wave continues at the present sample index;
    - ripple filter: the chain is rebuilt and **the ripple Kalman filter restarts** from
      P0; the differentiator, the encoder unwrapping and the plausibility state carry over;
    - control law: the LQG stage is rebuilt (observer from rest), ``prebuilt`` used when
      it matches; a new desired torque only swaps the desired-torque generator.
    """
    done = Applied()
    Ts = new.sample_period_s
    isr.cfg = new  # also rebuilds the sensor source on the new calibration
    if new.reference != old.reference:
        isr.reference = ReferenceGenerator(new.reference, Ts)
    if new.ripple != old.ripple:
        previous = isr.chain
        chain = TorqueFilterChain(new)
        chain.differentiator = previous.differentiator
        chain.encoder = previous.encoder
        chain.integrator = previous.integrator
        chain.angle = previous.angle
        chain.keep_plausibility(previous.plausibility)
        isr.chain = chain
        done.filter_restarted = True
    else:
        isr.chain.cfg = new
    if new.control != old.control:
        done.control_changed = True
        if not new.control.active:
            isr.control = None
        elif isr.control is None or new.control.law != old.control.law:
            if prebuilt is not None and prebuilt[0] == new.control:
                isr.control = prebuilt[1]
            else:
                isr.control = TorqueControl(new)
            done.control_rebuilt = True
        else:  # same law, new desired torque: the observer keeps its state
            isr.control.cfg = new.control
            isr.control.desired = ReferenceGenerator(new.control.desired.reference(), Ts)
    return done
