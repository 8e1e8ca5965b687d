"""The blocks of a simulation model (design.md "Model YAML"): their parameters, validation and dicts."""

from __future__ import annotations

import dataclasses
import math
import numbers
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from pipeline.errors import ModelError


DEFAULT_PID_FILTER_N = 10.0


class FieldError(ModelError):
    """A single invalid field; :func:`model_from_dict` re-raises it with its key path."""

    def __init__(self, message: str, *, key: str, value: Any, allowed: str) -> None:
        super().__init__(message)
        self.key = key
        self.value = value
        self.allowed = allowed


def is_real(value: Any) -> bool:
    """Whether ``value`` is a real number (not a bool).

    Parameters
    ----------
    value : any
        A value read from a model dict.
    """
    # bool is an int subclass; a YAML `k: yes` is a typo, not the number 1.
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def check_signal_name(value: Any, *, where: str, key: str) -> str:
    """``value`` if it is a valid signal name, else a :class:`FieldError`.

    Parameters
    ----------
    value : any
        The name as given.
    where : str
        The block or model it belongs to, for the message.
    key : str
        The field holding it.
    """
    if not isinstance(value, str) or not value or value != value.strip() or value[0] in "+-":
        raise FieldError(
            f"{where}: {key}={value!r} is not a valid signal name; names are non-empty "
            "strings without surrounding spaces and not starting with '-' or '+' "
            "(write '-name' only inside an input list to negate a signal)",
            key=key,
            value=value,
            allowed="a non-empty string not starting with '-' or '+'",
        )
    return value


def _strip_leading_zeros(coefficients: np.ndarray) -> np.ndarray:
    nonzero = np.flatnonzero(coefficients)
    return coefficients[nonzero[0]:] if nonzero.size else np.zeros(1)


@dataclass(frozen=True)
class Term:
    """One summed input of a block: ``k * signal``.

    Parameters
    ----------
    signal : str
        Name of a model input or of another block.
    k : float
        Weight (dimensionless scale); ``-1`` is written ``-name`` in YAML.
    """

    signal: str
    k: float = 1.0

    def __post_init__(self) -> None:
        check_signal_name(self.signal, where=f"input term {self.signal!r}", key="signal")
        if not is_real(self.k) or not math.isfinite(self.k):
            raise FieldError(
                f"input term {self.signal!r}: k={self.k!r} is not a finite number",
                key="k",
                value=self.k,
                allowed="a finite number",
            )
        object.__setattr__(self, "k", float(self.k))

    @classmethod
    def parse(cls, spec: Any) -> Term:
        """Parse the YAML form: ``"name"``, ``"-name"`` or ``{signal: name, k: 2.0}``.

        Parameters
        ----------
        spec : str or mapping
            As written in a block's ``input``/``inputs``.

        Returns
        -------
        Term

        Raises
        ------
        ModelError
            When `spec` is none of these forms.
        """
        if isinstance(spec, str):
            if spec.startswith("-"):
                return cls(signal=spec[1:], k=-1.0)
            return cls(signal=spec)
        if isinstance(spec, Mapping):
            unknown = sorted(set(spec) - {"signal", "k"})
            if unknown:
                raise FieldError(
                    f"input term {dict(spec)!r}: unknown key {unknown[0]!r}; a scaled "
                    "term has keys 'signal' and optional 'k'",
                    key=str(unknown[0]),
                    value=spec[unknown[0]],
                    allowed="keys 'signal' and 'k'",
                )
            if "signal" not in spec:
                raise FieldError(
                    f"input term {dict(spec)!r}: missing key 'signal'; write "
                    "{signal: name, k: 2.0}",
                    key="signal",
                    value=None,
                    allowed="a signal name",
                )
            return cls(signal=spec["signal"], k=spec.get("k", 1.0))
        raise FieldError(
            f"input term {spec!r}: expected 'name', '-name' or {{signal: name, k: 2.0}}",
            key="",
            value=spec,
            allowed="'name', '-name' or {signal: name, k: number}",
        )

    def to_spec(self) -> str | dict[str, Any]:
        """The YAML form (inverse of :meth:`parse`)."""
        if self.k == 1.0:
            return self.signal
        if self.k == -1.0:
            return f"-{self.signal}"
        return {"signal": self.signal, "k": self.k}


@dataclass(frozen=True, kw_only=True)
class Block:
    """Base of every block: a name and the summed input terms.

    Subclasses add their parameters as fields; ``TYPE`` is the YAML ``type``.

    Parameters
    ----------
    name : str
        Unique within the model; the block's output signal has this name.
    inputs : tuple of Term
        Summed to form the block's input ``u``.  May be empty only while a block is
        being built for :func:`insert_before`; a :class:`Model` requires at least one.
    """

    name: str
    inputs: tuple[Term, ...] = ()

    TYPE: ClassVar[str] = ""
    LINEAR: ClassVar[bool] = True
    #: Parameter that :func:`scale_gain` multiplies (None: see that function).
    GAIN_PARAMETER: ClassVar[str | None] = None

    def __post_init__(self) -> None:
        check_signal_name(self.name, where=f"{self.TYPE} block", key="name")
        if isinstance(self.inputs, (str, Term)) or not isinstance(self.inputs, Sequence):
            raise FieldError(
                f"{self._where}: inputs={self.inputs!r} must be a sequence of Term",
                key="inputs",
                value=self.inputs,
                allowed="a sequence of Term",
            )
        object.__setattr__(self, "inputs", tuple(self.inputs))
        for j, term in enumerate(self.inputs):
            if not isinstance(term, Term):
                raise FieldError(
                    f"{self._where}: inputs[{j}]={term!r} is not a Term "
                    "(use Term.parse('-name') for the YAML forms)",
                    key=f"inputs[{j}]",
                    value=term,
                    allowed="a Term",
                )
        self._check_parameters()

    # -- validation helpers -------------------------------------------------------
    @property
    def _where(self) -> str:
        return f"block {self.name!r} (type {self.TYPE})"

    def _fail(self, key: str, allowed: str) -> None:
        value = getattr(self, key)
        raise FieldError(
            f"{self._where}: {key}={value!r} is invalid; {allowed}",
            key=key,
            value=value,
            allowed=allowed,
        )

    def _real(
        self,
        key: str,
        *,
        minimum: float | None = None,
        strict: bool = False,
        allow_inf: bool = False,
    ) -> float:
        value = getattr(self, key)
        if minimum is None:
            bound = ""
        else:
            bound = f" {'>' if strict else '>='} {minimum:g}"
        if allow_inf:
            allowed = f"{key} must be a number{bound} (not NaN; -inf/inf allowed)"
        else:
            allowed = f"{key} must be a finite number{bound}"
        if not is_real(value) or math.isnan(value) or (not allow_inf and math.isinf(value)):
            self._fail(key, allowed)
        if minimum is not None and (value < minimum or (strict and value == minimum)):
            self._fail(key, allowed)
        object.__setattr__(self, key, float(value))
        return float(value)

    def _check_parameters(self) -> None:
        """Validate and normalise the subclass fields (override)."""

    # -- behaviour ----------------------------------------------------------------
    @property
    def parameters(self) -> dict[str, Any]:
        """The type-specific fields (everything except ``name`` and ``inputs``)."""
        return {
            f.name: getattr(self, f.name)
            for f in dataclasses.fields(self)
            if f.name not in ("name", "inputs")
        }

    def references(self) -> tuple[str, ...]:
        """Every signal name this block reads (its terms, plus scheduling signals)."""
        return tuple(term.signal for term in self.inputs)

    def transfer_function(self) -> tuple[np.ndarray, np.ndarray]:
        """Continuous ``(num, den)`` in descending powers of ``s``, without the delay.

        Leading zeros are stripped, so ``len(num) == len(den)`` means direct
        feedthrough.  Only for linear blocks.
        """
        raise ModelError(f"{self._where} is nonlinear and has no transfer function")

    @property
    def dead_time_s(self) -> float:
        """The block's dead time in seconds (0 for nonlinear blocks)."""
        return float(getattr(self, "delay_s", 0.0))

    @property
    def has_feedthrough(self) -> bool:
        """True when the output at sample k depends on the input at sample k.

        A block without feedthrough (dead time, or a strictly proper transfer function
        discretised with a zero-order hold) breaks loops.
        """
        if not self.LINEAR:
            return True
        if self.dead_time_s > 0.0:
            return False
        num, den = self.transfer_function()
        return bool(len(num) >= len(den) and np.any(num != 0.0))


class _LinearBlock(Block):
    """A linear block: takes ``delay_s`` (pure dead time, s, >= 0)."""

    def _check_delay(self) -> None:
        self._real("delay_s", minimum=0.0)


@dataclass(frozen=True, kw_only=True)
class Gain(_LinearBlock):
    """Static gain ``k`` (with optional dead time)."""

    k: float
    delay_s: float = 0.0
    TYPE: ClassVar[str] = "gain"
    GAIN_PARAMETER: ClassVar[str | None] = "k"

    def _check_parameters(self) -> None:
        self._real("k")
        self._check_delay()

    def transfer_function(self) -> tuple[np.ndarray, np.ndarray]:
        return np.array([self.k]), np.array([1.0])


@dataclass(frozen=True, kw_only=True)
class FirstOrder(_LinearBlock):
    """First-order lag ``k / (tau_s s + 1)``."""

    k: float
    tau_s: float
    delay_s: float = 0.0
    TYPE: ClassVar[str] = "first_order"
    GAIN_PARAMETER: ClassVar[str | None] = "k"

    def _check_parameters(self) -> None:
        self._real("k")
        self._real("tau_s", minimum=0.0, strict=True)
        self._check_delay()

    def transfer_function(self) -> tuple[np.ndarray, np.ndarray]:
        return np.array([self.k]), np.array([self.tau_s, 1.0])


@dataclass(frozen=True, kw_only=True)
class SecondOrder(_LinearBlock):
    """Second-order ``k wn² / (s² + 2 zeta wn s + wn²)``; ``wn`` in rad/s."""

    k: float
    wn: float
    zeta: float
    delay_s: float = 0.0
    TYPE: ClassVar[str] = "second_order"
    GAIN_PARAMETER: ClassVar[str | None] = "k"

    def _check_parameters(self) -> None:
        self._real("k")
        self._real("wn", minimum=0.0, strict=True)
        self._real("zeta", minimum=0.0)
        self._check_delay()

    def transfer_function(self) -> tuple[np.ndarray, np.ndarray]:
        wn2 = self.wn * self.wn
        return np.array([self.k * wn2]), np.array([1.0, 2.0 * self.zeta * self.wn, wn2])


@dataclass(frozen=True, kw_only=True)
class Transfer(_LinearBlock):
    """Rational ``num(s) / den(s)``, coefficients in descending powers of ``s``.

    Must be proper (numerator degree <= denominator degree after stripping leading
    zeros): an improper transfer function differentiates and cannot be simulated.
    """

    num: tuple[float, ...]
    den: tuple[float, ...]
    delay_s: float = 0.0
    TYPE: ClassVar[str] = "transfer"

    def _check_parameters(self) -> None:
        for key in ("num", "den"):
            value = getattr(self, key)
            ok = (
                isinstance(value, Sequence)
                and not isinstance(value, str)
                and len(value) > 0
                and all(is_real(v) and math.isfinite(v) for v in value)
            )
            if not ok:
                self._fail(key, f"{key} must be a non-empty list of finite numbers")
            object.__setattr__(self, key, tuple(float(v) for v in value))
        if not any(self.den):
            self._fail("den", "den must have a nonzero coefficient")
        num = _strip_leading_zeros(np.asarray(self.num))
        den = _strip_leading_zeros(np.asarray(self.den))
        if len(num) > len(den):
            self._fail(
                "num",
                f"the transfer function is improper (numerator degree {len(num) - 1} > "
                f"denominator degree {len(den) - 1}); add filter poles to den",
            )
        self._check_delay()

    def transfer_function(self) -> tuple[np.ndarray, np.ndarray]:
        return (
            _strip_leading_zeros(np.asarray(self.num)),
            _strip_leading_zeros(np.asarray(self.den)),
        )


@dataclass(frozen=True, kw_only=True)
class Integrator(_LinearBlock):
    """Integrator ``k / s`` (k in output units per input unit per second)."""

    k: float
    delay_s: float = 0.0
    TYPE: ClassVar[str] = "integrator"
    GAIN_PARAMETER: ClassVar[str | None] = "k"

    def _check_parameters(self) -> None:
        self._real("k")
        self._check_delay()

    def transfer_function(self) -> tuple[np.ndarray, np.ndarray]:
        return np.array([self.k]), np.array([1.0, 0.0])


@dataclass(frozen=True, kw_only=True)
class PI(_LinearBlock):
    """PI controller ``kp (1 + 1/(ti_s s))`` (ideal/ISA form)."""

    kp: float
    ti_s: float
    delay_s: float = 0.0
    TYPE: ClassVar[str] = "pi"
    GAIN_PARAMETER: ClassVar[str | None] = "kp"

    def _check_parameters(self) -> None:
        self._real("kp")
        self._real("ti_s", minimum=0.0, strict=True)
        self._check_delay()

    def transfer_function(self) -> tuple[np.ndarray, np.ndarray]:
        return self.kp * np.array([self.ti_s, 1.0]), np.array([self.ti_s, 0.0])


@dataclass(frozen=True, kw_only=True)
class PID(_LinearBlock):
    """PID ``kp (1 + 1/(ti_s s) + td_s s / (tf_s s + 1))`` with ``tf_s = td_s / n_filter``.

    The ideal derivative ``td_s s`` is improper; the first-order filter makes it
    realisable (high-frequency derivative gain ``kp n_filter``).  ``td_s = 0`` is a PI.
    """

    kp: float
    ti_s: float
    td_s: float
    n_filter: float = DEFAULT_PID_FILTER_N
    delay_s: float = 0.0
    TYPE: ClassVar[str] = "pid"
    GAIN_PARAMETER: ClassVar[str | None] = "kp"

    def _check_parameters(self) -> None:
        self._real("kp")
        self._real("ti_s", minimum=0.0, strict=True)
        self._real("td_s", minimum=0.0)
        self._real("n_filter", minimum=0.0, strict=True)
        self._check_delay()

    def transfer_function(self) -> tuple[np.ndarray, np.ndarray]:
        ti, td = self.ti_s, self.td_s
        if td == 0.0:
            return self.kp * np.array([ti, 1.0]), np.array([ti, 0.0])
        tf = td / self.n_filter
        # Common denominator ti s (tf s + 1):
        # ti s (tf s + 1) + (tf s + 1) + ti td s²
        num = np.array([ti * tf + ti * td, ti + tf, 1.0])
        den = np.array([ti * tf, ti, 0.0])
        return self.kp * num, den


@dataclass(frozen=True, kw_only=True)
class Sum(_LinearBlock):
    """Weighted sum of the input terms (optionally delayed)."""

    delay_s: float = 0.0
    TYPE: ClassVar[str] = "sum"

    def _check_parameters(self) -> None:
        self._check_delay()

    def transfer_function(self) -> tuple[np.ndarray, np.ndarray]:
        return np.array([1.0]), np.array([1.0])


@dataclass(frozen=True, kw_only=True)
class Deadband(Block):
    """Static deadband of total ``width``: 0 inside ``|u| <= width/2``, else ``u ∓ width/2``."""

    width: float
    TYPE: ClassVar[str] = "deadband"
    LINEAR: ClassVar[bool] = False

    def _check_parameters(self) -> None:
        self._real("width", minimum=0.0)


@dataclass(frozen=True, kw_only=True)
class Backlash(Block):
    """Backlash (play, hysteresis with memory) of total ``width``, as a worn valve.

    The output holds while the input moves within ``width`` of the last turning point
    and follows it at a distance ``width/2`` once it has: ``y_k = u_k - width/2`` when
    ``u_k > y_{k-1} + width/2``, ``u_k + width/2`` when ``u_k < y_{k-1} - width/2``,
    else ``y_{k-1}``.  The memory starts at rest (``y_{-1} = 0``, the deviation
    model's operating point), so a constant input inside the play gives 0.  Unlike
    :class:`Deadband` (a fixed zone around the operating point) the zone travels with
    the input: a valve that moves far still loses ``width`` at every reversal.
    """

    width: float
    TYPE: ClassVar[str] = "backlash"
    LINEAR: ClassVar[bool] = False

    def _check_parameters(self) -> None:
        self._real("width", minimum=0.0)


@dataclass(frozen=True, kw_only=True)
class Saturation(Block):
    """Static saturation ``clip(u, low, high)``; limits may be ``-inf``/``inf``."""

    low: float
    high: float
    TYPE: ClassVar[str] = "saturation"
    LINEAR: ClassVar[bool] = False

    def _check_parameters(self) -> None:
        self._real("low", allow_inf=True)
        self._real("high", allow_inf=True)
        if not self.low < self.high:
            self._fail("high", f"high must be greater than low={self.low!r}")


@dataclass(frozen=True, kw_only=True)
class OperatingPointGain(Block):
    """Gain scheduled on a signal: ``u (1 + slope * signal)`` (static, nonlinear).

    ``slope`` is the relative gain change per unit of ``signal`` (deviation units).
    """

    slope: float
    signal: str
    TYPE: ClassVar[str] = "operating_point_gain"
    LINEAR: ClassVar[bool] = False

    def _check_parameters(self) -> None:
        self._real("slope")
        check_signal_name(self.signal, where=self._where, key="signal")

    def references(self) -> tuple[str, ...]:
        return (*super().references(), self.signal)


#: Block types of a feedback controller: the blocks whose output a plant limits (e.g. to
#: 0-100 %) and whose measured output opens their loop
#: (:func:`pipeline.discrepancy.problem.loops_to_open`).
CONTROLLER_TYPES = ("pi", "pid")

#: YAML ``type`` -> block class.
BLOCK_TYPES: dict[str, type[Block]] = {
    cls.TYPE: cls
    for cls in (
        Gain,
        FirstOrder,
        SecondOrder,
        Transfer,
        Integrator,
        PI,
        PID,
        Sum,
        Deadband,
        Backlash,
        Saturation,
        OperatingPointGain,
    )
}
