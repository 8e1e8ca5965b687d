"""Block-diagram simulation models: specification, validation and round trip.

A model is a named set of SISO blocks wired by signal names (design.md, "Model YAML")::

    model:
      name: boiler_pressure
      inputs: [steam_flow]
      outputs: [turbine_pressure]
      blocks:
        - {name: feedforward, type: gain, input: steam_flow, k: 0.019}
        - {name: controller, type: pi, input: turbine_pressure, kp: -0.554, ti_s: 60}
        - {name: demand, type: sum, inputs: [controller, feedforward]}
        - {name: fuel, type: gain, input: demand, k: 65, delay_s: 8}
        - {name: drum, type: integrator, inputs: [fuel, -steam_flow], k: 0.000883}
        - {name: turbine_pressure, type: sum, inputs: [drum, {signal: steam_flow, k: -0.045}]}

This module is core: it takes an already-parsed mapping (:func:`model_from_dict`) and
returns frozen dataclasses; :func:`model_to_dict` gives back a mapping that re-validates
to an equal :class:`Model`.  Simulation lives in :mod:`pipeline.models.simulate`.

Block types and their transfer functions (``s`` in 1/s, every linear block may add
``delay_s`` of pure dead time, ``u`` is the block's summed input):

- ``gain`` (``k``): ``k``
- ``first_order`` (``k``, ``tau_s`` > 0): ``k / (tau_s s + 1)``
- ``second_order`` (``k``, ``wn`` > 0 in rad/s, ``zeta`` >= 0):
  ``k wn² / (s² + 2 zeta wn s + wn²)``
- ``transfer`` (``num``, ``den``): ``num(s) / den(s)``, descending powers, proper
- ``integrator`` (``k``): ``k / s``
- ``pi`` (``kp``, ``ti_s`` > 0): ``kp (1 + 1/(ti_s s))``
- ``pid`` (``kp``, ``ti_s`` > 0, ``td_s`` >= 0, optional ``n_filter`` > 0, default 10):
  ``kp (1 + 1/(ti_s s) + td_s s / (td_s/n_filter s + 1))`` -- the ideal derivative
  ``td_s s`` is improper; a lag of ``td_s / n_filter`` makes it realisable
- ``sum`` (inputs only): the weighted sum of its inputs
- ``deadband`` (``width`` >= 0): 0 for ``|u| <= width/2``, else ``u - sign(u) width/2``
  (static, continuous)
- ``backlash`` (``width`` >= 0): play with memory -- the output holds until the input
  has reversed by ``width``, then follows it ``width/2`` behind (a worn valve)
- ``saturation`` (``low`` < ``high``, either may be ±inf): ``clip(u, low, high)``
- ``operating_point_gain`` (``slope``, ``signal``: a signal name):
  ``u (1 + slope * signal)``; static gain scheduling, an extension beyond design.md for
  the discrepancy effect of the same name

``deadband``, ``backlash``, ``saturation`` and ``operating_point_gain`` are nonlinear and take no
``delay_s``.  A block reads ``input:`` (one term) or ``inputs:`` (a summed list).  A term
is ``name``, ``-name`` (negated) or ``{signal: name, k: 2.0}`` (scaled).  A term names a
model input or another block.

Loops are legal when every loop passes through a block without direct feedthrough:
``delay_s > 0`` or a strictly proper transfer function (lag, integrator, ``second_order``,
strictly proper ``transfer``).  Such a block's output at sample ``k`` depends only on
samples before ``k`` once discretised with a zero-order hold, so the simulation can
evaluate it before its input is known.  A loop made only of feedthrough blocks is an
algebraic loop and a :class:`~pipeline.errors.ModelError` naming its blocks.

Modifying a model (the discrepancy workflow): blocks are frozen dataclasses, so
``dataclasses.replace(block, kp=1.2 * block.kp)`` or :func:`scale_gain`,
``Model.with_block`` (replace or append), :func:`insert_after` (e.g. an extra lag after a
block, keeping the block's name on the downstream end so outputs and consumers are
unchanged) and :func:`insert_before` (e.g. a deadband on a block's input).  Every
constructor validates, so a modified model is always a valid model.
"""

from __future__ import annotations

import dataclasses
import difflib
import graphlib
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from pipeline.models.blocks import (
    BLOCK_TYPES,
    Block,
    FieldError,
    OperatingPointGain,
    Sum,
    Term,
    Transfer,
    check_signal_name,
    is_real,
)
from pipeline.errors import ModelError


MAX_BLOCKS = 100
"""Most blocks a model file may hold (:func:`model_from_dict`).  Why 100: the largest
shipped model has 13 blocks; one simulation of a day at 1 s takes 1.5 s at 100 blocks
and 25 s at 1000 (the interconnection is dense in the block count), and the discrepancy
workflow simulates the model hundreds of times and screens every block: 50 blocks took
150 s on one hour of record, 200 blocks more than 10 minutes, and a 10,000-block model
ran out of memory after 245 s.  The effects the workflow adds to a model do not count."""


def _suggest(name: str, candidates: Sequence[str]) -> str:
    close = difflib.get_close_matches(name, list(candidates), n=1)
    return f" (did you mean {close[0]!r}?)" if close else ""


@dataclass(frozen=True, kw_only=True)
class Model:
    """A validated block-diagram model.

    Parameters
    ----------
    name : str
        Model name.
    inputs : tuple of str
        Measured signals driving the model (deviation units).
    outputs : tuple of str
        Block names compared with measured signals.
    blocks : tuple of Block
        In any order; loops allowed through blocks without feedthrough.
    description : str
        Free text (e.g. which discrepancy effects were added).

    Raises
    ------
    ModelError
        On duplicate names, unknown signal references, outputs not naming a block, a
        block with no inputs, or an algebraic loop; the message gives the key path
        (``model.blocks[3].inputs[1]``).
    """

    name: str
    inputs: tuple[str, ...]
    outputs: tuple[str, ...]
    blocks: tuple[Block, ...]
    description: str = ""

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name.strip():
            raise ModelError(f"model.name: {self.name!r} is invalid; give a non-empty string")
        if not isinstance(self.description, str):
            raise ModelError(f"model.description: {self.description!r} must be a string")
        for key in ("inputs", "outputs", "blocks"):
            value = getattr(self, key)
            if isinstance(value, (str, Mapping)) or not isinstance(value, Sequence):
                raise ModelError(f"model.{key}: {value!r} must be a list")
            object.__setattr__(self, key, tuple(value))
        self._validate()

    def _validate(self) -> None:
        self._validate_inputs()
        index = self._validate_block_names()
        self._validate_references(index)
        self._validate_outputs(index)
        cycle = _algebraic_loop(self.blocks)
        if cycle:
            path = " -> ".join(repr(name) for name in cycle)
            raise ModelError(
                f"model.blocks: algebraic loop through blocks {path}: every block in it "
                "passes its input to its output within the same sample; put a delay_s > 0 "
                "or a lag/integrator in the loop"
            )

    def _validate_inputs(self) -> None:
        for i, name in enumerate(self.inputs):
            try:
                check_signal_name(name, where=f"model.inputs[{i}]", key="input")
            except FieldError as exc:
                raise ModelError(
                    f"model.inputs[{i}]: {name!r} is not a valid signal name; {exc.allowed}"
                ) from None
            if name in self.inputs[:i]:
                raise ModelError(
                    f"model.inputs[{i}]: duplicate input name {name!r}; list each input once"
                )

    def _validate_block_names(self) -> dict[str, int]:
        """Block name -> index, after checking that the names are unique and not inputs."""
        if not self.blocks:
            raise ModelError("model.blocks: the model has no blocks; add at least one block")
        index: dict[str, int] = {}
        for i, block in enumerate(self.blocks):
            if not isinstance(block, Block):
                raise ModelError(f"model.blocks[{i}]: {block!r} is not a Block")
            if block.name in index:
                raise ModelError(
                    f"model.blocks[{i}].name: duplicate block name {block.name!r} (also "
                    f"model.blocks[{index[block.name]}]); block names must be unique"
                )
            if block.name in self.inputs:
                raise ModelError(
                    f"model.blocks[{i}].name: {block.name!r} is also a model input; a "
                    "signal name must be either an input or a block"
                )
            index[block.name] = i
        return index

    def _validate_references(self, index: dict[str, int]) -> None:
        signals = (*self.inputs, *index)
        for i, block in enumerate(self.blocks):
            if not block.inputs:
                raise ModelError(
                    f"model.blocks[{i}].inputs: block {block.name!r} reads no signal; give "
                    "'input: name' or 'inputs: [a, -b]'"
                )
            for j, term in enumerate(block.inputs):
                if term.signal not in signals:
                    raise ModelError(
                        f"model.blocks[{i}].inputs[{j}]: unknown signal {term.signal!r} in "
                        f"block {block.name!r}{_suggest(term.signal, signals)}; a term names "
                        f"a model input {list(self.inputs)} or a block {list(index)}"
                    )
            if isinstance(block, OperatingPointGain) and block.signal not in signals:
                raise ModelError(
                    f"model.blocks[{i}].signal: unknown signal {block.signal!r} in block "
                    f"{block.name!r}{_suggest(block.signal, signals)}; it names a model "
                    f"input {list(self.inputs)} or a block {list(index)}"
                )

    def _validate_outputs(self, index: dict[str, int]) -> None:
        if not self.outputs:
            raise ModelError("model.outputs: empty; name at least one block as an output")
        for i, name in enumerate(self.outputs):
            if name not in index:
                raise ModelError(
                    f"model.outputs[{i}]: {name!r} is not a block{_suggest(name, list(index))};"
                    f" outputs must name blocks: {list(index)}"
                )
            if name in self.outputs[:i]:
                raise ModelError(f"model.outputs[{i}]: duplicate output {name!r}")

    # -- lookups and modification -------------------------------------------------
    @property
    def block_names(self) -> tuple[str, ...]:
        """Block names in model order."""
        return tuple(block.name for block in self.blocks)

    @property
    def is_linear(self) -> bool:
        """True when every block is linear (no deadband/backlash/saturation/scheduling)."""
        return all(block.LINEAR for block in self.blocks)

    def block(self, name: str) -> Block:
        """The block called `name`.

        Parameters
        ----------
        name : str

        Returns
        -------
        Block

        Raises
        ------
        ModelError
            No such block (with a close-match suggestion).
        """
        for block in self.blocks:
            if block.name == name:
                return block
        raise ModelError(
            f"model {self.name!r}: no block {name!r}{_suggest(name, self.block_names)}; "
            f"blocks are {list(self.block_names)}"
        )

    def with_block(self, block: Block) -> Model:
        """A copy with `block` replacing the same-named block, or appended if new.

        Parameters
        ----------
        block : Block

        Returns
        -------
        Model
            Validated like any :class:`Model`.
        """
        if block.name in self.block_names:
            blocks = tuple(block if b.name == block.name else b for b in self.blocks)
        else:
            blocks = (*self.blocks, block)
        return dataclasses.replace(self, blocks=blocks)


def _algebraic_loop(blocks: Sequence[Block]) -> list[str]:
    """Blocks of one cycle made only of feedthrough blocks (empty list if none)."""
    names = {block.name for block in blocks}
    graph: dict[str, set[str]] = {}
    for block in blocks:
        # Only a feedthrough block needs its inputs within the same sample.
        needs = set(block.references()) & names if block.has_feedthrough else set()
        graph[block.name] = needs
    try:
        tuple(graphlib.TopologicalSorter(graph).static_order())
    except graphlib.CycleError as exc:
        # graphlib lists each node before the node it feeds: signal-flow order, with
        # the first node repeated at the end.
        return list(exc.args[1])
    return []


# -- dict round trip --------------------------------------------------------------
_MODEL_KEYS = ("name", "description", "inputs", "outputs", "blocks")


def _string_list(value: Any, path: str) -> list[str]:
    if isinstance(value, str) or not isinstance(value, Sequence):
        raise ModelError(f"{path}: {value!r} must be a list of names, e.g. [steam_flow]")
    for j, item in enumerate(value):
        if not isinstance(item, str):
            raise ModelError(f"{path}[{j}]: {item!r} must be a name (a string)")
    return list(value)


def _block_from_dict(spec: Any, path: str) -> Block:
    if not isinstance(spec, Mapping):
        raise ModelError(
            f"{path}: {spec!r} must be a mapping like {{name: fuel, type: gain, "
            "input: demand, k: 65}"
        )
    for key in ("name", "type"):
        if key not in spec:
            raise ModelError(f"{path}.{key}: missing; every block needs 'name' and 'type'")
    block_type = spec["type"]
    if block_type not in BLOCK_TYPES:
        raise ModelError(
            f"{path}.type: unknown block type {block_type!r}"
            f"{_suggest(str(block_type), list(BLOCK_TYPES))}; allowed: "
            f"{', '.join(BLOCK_TYPES)}"
        )
    cls = BLOCK_TYPES[block_type]
    fields = {f.name: f for f in dataclasses.fields(cls) if f.name not in ("name", "inputs")}
    required = [
        name
        for name, f in fields.items()
        if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
    ]
    for key in spec:
        if key not in fields and key not in ("name", "type", "input", "inputs"):
            extra = "; nonlinear blocks take no delay_s" if key == "delay_s" else ""
            raise ModelError(
                f"{path}.{key}: unknown parameter for block type {block_type}"
                f"{_suggest(str(key), list(fields))}; allowed: "
                f"{', '.join(fields) or '(none besides name, type, input/inputs)'}{extra}"
            )
    for key in required:
        if key not in spec:
            raise ModelError(
                f"{path}.{key}: missing; block type {block_type} requires "
                f"{', '.join(required)}"
            )
    if ("input" in spec) == ("inputs" in spec):
        raise ModelError(
            f"{path}: block {spec['name']!r} needs exactly one of 'input: name' or "
            "'inputs: [a, -b, {signal: c, k: 2}]'"
        )
    if "input" in spec:
        raw_terms: list[Any] = [spec["input"]]
        term_paths = [f"{path}.input"]
    else:
        raw = spec["inputs"]
        if isinstance(raw, (str, Mapping)) or not isinstance(raw, Sequence) or not raw:
            raise ModelError(
                f"{path}.inputs: {raw!r} must be a non-empty list, e.g. [fuel, -steam_flow]"
            )
        raw_terms = list(raw)
        term_paths = [f"{path}.inputs[{j}]" for j in range(len(raw_terms))]
    terms = []
    for raw_term, term_path in zip(raw_terms, term_paths, strict=True):
        try:
            terms.append(Term.parse(raw_term))
        except FieldError as exc:
            key = f".{exc.key}" if exc.key else ""
            raise ModelError(
                f"{term_path}{key}: {exc.value!r} is invalid; {exc.allowed}"
            ) from None
    kwargs = {key: spec[key] for key in fields if key in spec}
    try:
        return cls(name=spec["name"], inputs=tuple(terms), **kwargs)
    except FieldError as exc:
        raise ModelError(
            f"{path}.{exc.key}: {exc.value!r} is invalid for block {spec['name']!r} "
            f"(type {block_type}); {exc.allowed}"
        ) from None


def model_from_dict(d: Mapping[str, Any], *, max_blocks: int | None = MAX_BLOCKS) -> Model:
    """Validate a parsed model mapping and build a :class:`Model`.

    Parameters
    ----------
    d : mapping
        Either ``{"model": {...}}`` (a model YAML file) or the inner mapping (a model
        given inline in a job file), as parsed from YAML: ``name``, ``inputs``,
        ``outputs``, ``blocks`` and optional ``description``.
    max_blocks : int or None
        Most blocks allowed (:data:`MAX_BLOCKS`), checked before any block is built;
        None for no bound (a model the workflow itself augmented).

    Returns
    -------
    Model

    Raises
    ------
    ModelError
        With the key path (``model.blocks[3].k``), the bad value and what is allowed:
        more than `max_blocks` blocks, unknown key, type or parameter, missing
        parameter, out-of-range value, unknown
        signal, duplicate name, output not naming a block, algebraic loop.
    """
    if not isinstance(d, Mapping):
        raise ModelError(f"model: expected a mapping, got {type(d).__name__}")
    inner = d["model"] if set(d) == {"model"} else d
    if not isinstance(inner, Mapping):
        raise ModelError(f"model: expected a mapping, got {type(inner).__name__}")
    for key in inner:
        if key not in _MODEL_KEYS:
            raise ModelError(
                f"model.{key}: unknown key{_suggest(str(key), _MODEL_KEYS)}; allowed: "
                f"{', '.join(_MODEL_KEYS)}"
            )
    for key in ("name", "inputs", "outputs", "blocks"):
        if key not in inner:
            raise ModelError(f"model.{key}: missing; a model needs name, inputs, outputs, blocks")
    blocks_spec = inner["blocks"]
    if isinstance(blocks_spec, (str, Mapping)) or not isinstance(blocks_spec, Sequence):
        raise ModelError(f"model.blocks: {blocks_spec!r} must be a list of block mappings")
    if max_blocks is not None and len(blocks_spec) > max_blocks:
        raise ModelError(
            f"model.blocks: {len(blocks_spec)} blocks; a model may have at most {max_blocks} "
            "(the simulation and the discrepancy search grow with the block count) -- lump "
            "chains of blocks into one 'transfer' block (num/den) or split the model into "
            "one model per unit")
    blocks = tuple(
        _block_from_dict(spec, f"model.blocks[{i}]") for i, spec in enumerate(blocks_spec)
    )
    return Model(
        name=inner["name"],
        description=inner.get("description", ""),
        inputs=tuple(_string_list(inner["inputs"], "model.inputs")),
        outputs=tuple(_string_list(inner["outputs"], "model.outputs")),
        blocks=blocks,
    )


def _plain(value: Any) -> Any:
    if isinstance(value, tuple):
        return [float(v) for v in value]
    return value


def model_to_dict(model: Model) -> dict[str, Any]:
    """The ``{"model": {...}}`` mapping of `model` (plain lists/str/float; YAML-ready).

    ``model_from_dict(model_to_dict(m)) == m``.  Parameters equal to their defaults
    (``delay_s: 0``, ``n_filter: 10``) are left out; ``±inf`` saturation limits are
    floats (YAML ``.inf``).

    Parameters
    ----------
    model : Model
        The model to write out.
    """
    blocks = []
    for block in model.blocks:
        entry: dict[str, Any] = {"name": block.name, "type": block.TYPE}
        specs = [term.to_spec() for term in block.inputs]
        if len(specs) == 1 and isinstance(specs[0], str) and not isinstance(block, Sum):
            entry["input"] = specs[0]
        else:
            entry["inputs"] = specs
        for f in dataclasses.fields(block):
            if f.name in ("name", "inputs"):
                continue
            value = getattr(block, f.name)
            if f.default is not dataclasses.MISSING and value == f.default:
                continue
            entry[f.name] = _plain(value)
        blocks.append(entry)
    inner: dict[str, Any] = {"name": model.name}
    if model.description:
        inner["description"] = model.description
    inner.update(
        inputs=list(model.inputs),
        outputs=list(model.outputs),
        blocks=blocks,
    )
    return {"model": inner}


# -- modification helpers ---------------------------------------------------------
def scale_gain(block: Block, factor: float) -> Block:
    """`block` with its gain multiplied by `factor` (the catalogue's ``gain`` effect).

    ``k`` for gain/first_order/second_order/integrator, ``kp`` for pi/pid, the
    numerator for transfer, every term weight for sum.

    Parameters
    ----------
    block : Block
        A linear block.
    factor : float
        Multiplier (dimensionless; 1 leaves the block unchanged).

    Returns
    -------
    Block
        A new block of the same type and name.

    Raises
    ------
    ModelError
        For nonlinear blocks, which have no gain to scale.
    """
    if not is_real(factor) or not math.isfinite(factor):
        raise ModelError(f"scale_gain: factor={factor!r} must be a finite number")
    if block.GAIN_PARAMETER is not None:
        key = block.GAIN_PARAMETER
        return dataclasses.replace(block, **{key: factor * getattr(block, key)})
    if isinstance(block, Transfer):
        return dataclasses.replace(block, num=tuple(factor * v for v in block.num))
    if isinstance(block, Sum):
        inputs = tuple(dataclasses.replace(t, k=factor * t.k) for t in block.inputs)
        return dataclasses.replace(block, inputs=inputs)
    raise ModelError(
        f"{block._where}: nonlinear block has no gain to scale; apply the gain effect to "
        "a linear block"
    )


def insert_after(model: Model, name: str, *, block: Block, upstream_name: str) -> Model:
    """Insert `block` on the output of block `name`, keeping `name` downstream.

    The existing block `name` is renamed `upstream_name`; `block` must be called `name`
    and read `upstream_name`.  Consumers and outputs that read `name` therefore read the
    inserted block without rewiring (outputs keep their measured-signal names).

    Parameters
    ----------
    model : Model
    name : str
        The block whose output gets the new block.
    block : Block
        The inserted block, named `name`, reading `upstream_name`.
    upstream_name : str
        New name of the original block (must not exist yet).

    Returns
    -------
    Model
        Validated; raises ModelError as :class:`Model` does (e.g. a name clash).

    Example: an extra 20 s lag after ``fuel``::

        insert_after(m, "fuel", upstream_name="fuel_raw",
                     block=FirstOrder(name="fuel", inputs=(Term("fuel_raw"),), k=1, tau_s=20))
    """
    original = model.block(name)
    if block.name != name:
        raise ModelError(
            f"insert_after: the inserted block is called {block.name!r}; it must take the "
            f"name {name!r} so consumers and outputs read it"
        )
    if upstream_name not in block.references():
        raise ModelError(
            f"insert_after: the inserted block {name!r} does not read {upstream_name!r}; "
            f"give it an input Term({upstream_name!r})"
        )
    renamed = dataclasses.replace(original, name=upstream_name)
    blocks = [renamed if b.name == name else b for b in model.blocks]
    position = model.block_names.index(name)
    blocks.insert(position + 1, block)
    return dataclasses.replace(model, blocks=tuple(blocks))


def insert_before(model: Model, name: str, *, block: Block) -> Model:
    """Insert `block` on the input of block `name` (e.g. a deadband on its input).

    `block` must have no inputs of its own: it takes over the terms of block `name`,
    which then reads `block` alone.

    Parameters
    ----------
    model : Model
    name : str
        The block whose input gets the new block.
    block : Block
        Built with ``inputs=()`` and a new, unique name.

    Returns
    -------
    Model
        Validated like any :class:`Model`.
    """
    original = model.block(name)
    if block.inputs:
        raise ModelError(
            f"insert_before: block {block.name!r} already has inputs "
            f"{[t.signal for t in block.inputs]}; build it with inputs=() so it takes over "
            f"the inputs of {name!r}"
        )
    moved = dataclasses.replace(block, inputs=original.inputs)
    rewired = dataclasses.replace(original, inputs=(Term(block.name),))
    blocks = [rewired if b.name == name else b for b in model.blocks]
    position = model.block_names.index(name)
    blocks.insert(position, moved)
    return dataclasses.replace(model, blocks=tuple(blocks))


def open_at(model: Model, names: Sequence[str]) -> Model:
    """The model with its loops opened at blocks `names`: each becomes a model input.

    The blocks called `names` (controllers whose output is measured) are removed, their
    names join ``model.inputs`` -- so every block that read a controller now reads the
    measured signal of the same name -- and they leave ``model.outputs``.  Blocks that
    then feed nothing (a controller's error sum) are removed too.

    Parameters
    ----------
    model : Model
    names : sequence of str
        Blocks that are outputs of `model`.

    Returns
    -------
    Model
        Validated like any :class:`Model`.

    Raises
    ------
    ModelError
        A name that is not an output block of `model`, or nothing left to compare.
    """
    names = tuple(names)
    for name in names:
        if name not in model.outputs:
            raise ModelError(f"model {model.name!r}: cannot open the loop at {name!r}: it is "
                             f"not one of the outputs {list(model.outputs)}")
    outputs = tuple(o for o in model.outputs if o not in names)
    if not outputs:
        raise ModelError(f"model {model.name!r}: opening the loops at {list(names)} leaves "
                         "no output to compare")
    blocks = [b for b in model.blocks if b.name not in names]
    while True:  # drop what no longer feeds an output (a controller's error sum)
        read = set(outputs).union(*(b.references() for b in blocks))
        kept = [b for b in blocks if b.name in read]
        if len(kept) == len(blocks):
            break
        blocks = kept
    return dataclasses.replace(model, inputs=(*model.inputs, *names), outputs=outputs,
                               blocks=tuple(blocks))
