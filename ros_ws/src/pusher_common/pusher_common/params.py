"""Node settings as declared ROS parameters, with the old command-line flags as aliases.

A node lists its settings once, as :class:`Param` entries; from that list come

- the parameter declarations, each with a ``ParameterDescriptor`` (description, range,
  choices, ``read_only`` for what cannot change while the node runs), so ``--params-file``,
  ``-p name:=value``, launch files and ``ros2 param`` all reach them;
- the argparse flags (``--checkpoint PATH`` for ``checkpoint``), which only set the
  parameter's starting value (a flag wins over ``-p`` and a params file);
- one validation for start-up and run-time changes alike: a bad value at start is a
  :class:`~offline_rl_core.common.errors.UserError` naming the parameter, a bad ``ros2 param set``
  is refused with the same reason.

A parameter that is not read-only must take effect when set: the node passes
``on_change(name, value)``, called after a change was accepted; settings without such
handling are declared read-only, so ``ros2 param set`` is refused rather than ignored.
A node may also pass ``check(name, value) -> reason or None`` to refuse a run-time value
that is well-typed but unusable (a checkpoint that does not load).
"""

from __future__ import annotations

import argparse
import difflib
import math
import typing
from dataclasses import dataclass
from typing import Any, Callable, Sequence

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.parameter import Parameter

from offline_rl_core.common.errors import UserError

INT_MIN, INT_MAX = -(2**63), 2**63 - 1


@dataclass(frozen=True)
class Param:
    """One node setting.

    ``default`` fixes the type (bool, int, float, str, or a list of str); ``kind`` gives it
    when ``default`` is None (the parameter then starts unset, e.g. an optional path).
    ``low``/``high`` bound numbers (inclusive); ``choices`` lists the allowed strings.
    ``flag`` is the command-line alias (``"--hold-steps"``), or None for none.
    """

    name: str
    default: Any
    description: str
    low: float | None = None
    high: float | None = None
    choices: tuple = ()
    read_only: bool = False
    flag: str | None = None
    kind: type | None = None

    @property
    def type(self) -> type:
        if self.kind is not None:
            return self.kind
        if self.default is None:
            raise TypeError(f"parameter {self.name}: give kind= when the default is None")
        return type(self.default)

    def descriptor(self) -> ParameterDescriptor:
        d = ParameterDescriptor(name=self.name, description=self.description, read_only=self.read_only)
        if self.type is float:
            if self.default is not None:
                # ints are accepted for a float (``-p hold_ms:=100``), so the type is checked here
                d.dynamic_typing = True
            d.floating_point_range = [FloatingPointRange(
                from_value=-math.inf if self.low is None else float(self.low),
                to_value=math.inf if self.high is None else float(self.high), step=0.0)]
        elif self.type is int and (self.low is not None or self.high is not None):
            d.integer_range = [IntegerRange(
                from_value=INT_MIN if self.low is None else int(self.low),
                to_value=INT_MAX if self.high is None else int(self.high), step=1)]
        if self.choices:
            d.additional_constraints = "one of: " + ", ".join(map(str, self.choices))
        return d

    def check(self, value) -> tuple[Any, str | None]:
        """Check a value: (it in this parameter's type, None) or (None, why it is refused)."""
        kind = self.type
        if value is None:
            return (None, None) if self.default is None or kind is list else (None, "has no value")
        if kind is float:
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                return None, f"expected a number, got {value!r}"
            value = float(value)
            if not math.isfinite(value):
                return None, f"must be finite, got {value}"
        elif kind is list:
            value = list(value)
        elif kind is int and (isinstance(value, bool) or not isinstance(value, int)):
            return None, f"expected an integer, got {value!r}"
        elif not isinstance(value, kind):
            return None, f"expected {kind.__name__}, got {value!r}"
        if kind in (int, float):
            if self.low is not None and value < self.low:
                return None, f"must be >= {self.low}, got {value}"
            if self.high is not None and value > self.high:
                return None, f"must be <= {self.high}, got {value}"
        if self.choices and value not in self.choices:
            return None, f"must be one of {', '.join(map(str, self.choices))}; got {value!r}"
        return value, None


# ---------------------------------------------------------------- command-line aliases
def add_flags(parser: argparse.ArgumentParser, params: Sequence[Param]) -> None:
    """Add each parameter's ``flag``; a flag left out leaves the parameter alone."""
    for p in params:
        if not p.flag:
            continue
        common = dict(dest=p.name, default=argparse.SUPPRESS, help=f"{p.description} (parameter {p.name})")
        if p.type is bool:
            parser.add_argument(p.flag, action=argparse.BooleanOptionalAction, **common)
        elif p.type is list:
            parser.add_argument(p.flag, action="append", metavar=p.name.upper(), **common)
        else:
            parser.add_argument(p.flag, type=p.type, choices=p.choices or None, **common)


def overrides_from_flags(params: Sequence[Param], args: argparse.Namespace | None) -> list[Parameter]:
    """Parameter overrides for the flags given on the command line (for ``Node(parameter_overrides=)``)."""
    given = vars(args) if args is not None else {}
    return [Parameter(p.name, value=given[p.name]) for p in params if p.flag and p.name in given]


# ---------------------------------------------------------------- declaring
class Settings:
    """A node's declared parameters; ``settings.name`` is the current value."""

    def __init__(self, node, params: Sequence[Param], on_change: Callable[[str, Any], None] | None = None,
                 check: Callable[[str, Any], str | None] | None = None):
        self._node = node
        self._params = {p.name: p for p in params}
        self._on_change = on_change
        self._check = None  # only for run-time changes: the node checks its starting values itself
        self._values: dict[str, Any] = {}
        node.add_on_set_parameters_callback(self._validate)
        for p in params:
            if not p.read_only and on_change is None:
                raise TypeError(f"parameter {p.name} can change at run time but the node handles no change")
            try:
                if p.default is None or (p.type is list and not p.default):
                    type_ = Parameter.Type.STRING_ARRAY if p.type is list else Parameter.Type.from_parameter_value(
                        p.type())
                    declared = node.declare_parameter(p.name, type_, p.descriptor())
                else:
                    declared = node.declare_parameter(p.name, p.default, p.descriptor())
            except (InvalidParameterValueException, InvalidParameterTypeException) as exc:
                reason = str(exc).split("Reason: ", 1)[-1].removesuffix(f": {p.name}")
                named = reason if reason.startswith("parameter ") else f"parameter {p.name}: {reason}"
                raise UserError(named) from None
            self._values[p.name] = p.check(declared.value)[0]
        _refuse_unknown_overrides(node, params)
        node.add_post_set_parameters_callback(self._changed)
        self._check = check

    def __getattr__(self, name: str):
        try:
            return self.__dict__["_values"][name]
        except KeyError:
            raise AttributeError(name) from None

    def as_dict(self) -> dict[str, Any]:
        return dict(self._values)

    def _validate(self, parameters: list[Parameter]) -> SetParametersResult:
        for parameter in parameters:
            spec = self._params.get(parameter.name)
            if spec is None:
                continue  # rclpy's own (use_sim_time, ...)
            value, why = spec.check(parameter.value)
            if why is None and self._check is not None:
                why = self._check(parameter.name, value)
            if why:
                return SetParametersResult(successful=False, reason=f"parameter {parameter.name}: {why}")
        return SetParametersResult(successful=True)

    def _changed(self, parameters: list[Parameter]) -> None:
        for parameter in parameters:
            spec = self._params.get(parameter.name)
            if spec is None:
                continue
            value = spec.check(parameter.value)[0]
            changed = self._values.get(parameter.name, value) != value
            self._values[parameter.name] = value
            if changed and self._on_change is not None:
                self._on_change(parameter.name, value)


def _refuse_unknown_overrides(node, params: Sequence[Param]) -> None:
    """Refuse a ``-p`` or params-file value for a parameter the node does not have.

    rclpy would drop a misspelt one silently and the node would run on the default.
    """
    given = getattr(node, "_parameter_overrides", {})  # rclpy keeps no public list of them
    declared = set(node._parameters)  # noqa: SLF001 - ours, and rclpy's own (use_sim_time, ...)
    # qos_overrides.* only apply to publishers made with QoS overriding options: rclpy's, not ours
    unknown = sorted(name for name in given if name not in declared and not name.startswith("qos_overrides."))
    if unknown:
        names = [p.name for p in params]
        close = difflib.get_close_matches(unknown[0], names, n=1)
        hint = f"; did you mean {close[0]}?" if close else ""
        raise UserError(f"unknown parameter {unknown[0]!r} for node {node.get_name()}{hint} "
                        f"(its parameters: {', '.join(names)})")


def params_from_parser(parser: argparse.ArgumentParser, read_only: bool = True) -> list[Param]:
    """Parameters for every option of an existing argparse parser (its dests and defaults).

    For a node whose flags are defined elsewhere (the trainer shares ``offline-rl train``'s):
    each option becomes a parameter of the option's type, described by its help text.
    """
    params = []
    for action in parser._actions:  # noqa: SLF001 - argparse has no public listing
        if not action.option_strings or action.dest in ("help",) or action.dest is argparse.SUPPRESS:
            continue
        flag = next((o for o in action.option_strings if o.startswith("--") and not o.startswith("--no-")),
                    action.option_strings[0])
        description = (action.help or action.dest.replace("_", " ")) % {"default": action.default} \
            if action.help and "%(default)" in action.help else (action.help or action.dest.replace("_", " "))
        if isinstance(action, argparse.BooleanOptionalAction) or isinstance(action.const, bool):
            default, kind = bool(action.default), bool
        elif isinstance(action, argparse._AppendAction):  # noqa: SLF001
            default, kind = list(action.default or []), list
        else:
            kind = action.type if isinstance(action.type, type) else None  # a parsing function: its return type
            if kind is None and callable(action.type):
                kind = typing.get_type_hints(action.type).get("return")
            kind = kind if isinstance(kind, type) else type(action.default) if action.default is not None else str
            default = action.default
        params.append(Param(action.dest, default, description, choices=tuple(action.choices or ()),
                            read_only=read_only, flag=flag, kind=kind))
    return params
