"""Parameters declared from a table, with descriptors (description, ranges) and validation
that *refuses* a bad value with a clear message (as image_tools' cam2image does), and the
``main()`` shape of ros2/demos' talker shared by the nodes.

A table maps a parameter name to a :class:`Param`. :func:`declare_all` declares every entry
with a ``ParameterDescriptor`` and returns the validated values; a refused value raises
:class:`ParameterError` at start, and a later ``ros2 param set`` of a refused value is
rejected by :func:`install_set_callback`.
"""
from __future__ import annotations

import math
import signal
import sys
from dataclasses import dataclass

import numpy as np
import rclpy
import rclpy.executors
from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                SetParametersResult)
from rclpy.exceptions import (InvalidParameterTypeException,
                              InvalidParameterValueException)
from rclpy.executors import ExternalShutdownException
from rclpy.signals import SignalHandlerOptions


class ParameterError(ValueError):
    """A parameter value is refused."""


@dataclass(frozen=True)
class Param:
    """One parameter: default, description, and constraints.

    range    (lo, hi) inclusive for numbers; choices: allowed strings; size: length of an
    array parameter (its entries must be finite; > 0 too with ``positive``); read_only:
    cannot change after start.
    """

    default: object
    description: str
    range: tuple | None = None
    choices: tuple | None = None
    size: int | None = None
    read_only: bool = False
    positive: bool = False

    def descriptor(self) -> ParameterDescriptor:
        d = ParameterDescriptor(description=self.description, read_only=self.read_only)
        if self.choices:
            d.additional_constraints = f'one of {list(self.choices)}'
        if self.size:
            d.additional_constraints = f'{self.size} finite numbers'
        if self.range is not None:
            lo, hi = self.range
            if isinstance(self.default, bool):
                pass
            elif isinstance(self.default, int):
                d.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=1)]
            elif isinstance(self.default, float):
                d.floating_point_range = [FloatingPointRange(from_value=float(lo),
                                                             to_value=float(hi), step=0.0)]
        return d


def check(name: str, p: Param, value):
    """``value`` if ``p`` accepts it; :class:`ParameterError` with a clear message otherwise."""
    if p.choices is not None and value not in p.choices:
        raise ParameterError(f'{name} must be one of {list(p.choices)}, got {value!r}')
    if p.size is not None:
        arr = np.asarray(value, dtype=float)
        if arr.shape != (p.size,):
            raise ParameterError(f'{name} needs {p.size} numbers, got {len(value)}')
        if not np.all(np.isfinite(arr)):
            raise ParameterError(f'{name} contains NaN or inf: {list(value)}')
        if p.positive and np.any(arr <= 0):
            raise ParameterError(f'{name} must be > 0, got {list(value)}')
    if isinstance(p.default, (int, float)) and not isinstance(p.default, bool):
        if not math.isfinite(value):
            raise ParameterError(f'{name} must be finite, got {value}')
        if p.range is not None and not p.range[0] <= value <= p.range[1]:
            raise ParameterError(f'{name} must be in [{p.range[0]}, {p.range[1]}], '
                                 f'got {value}')
    return value


def declare_all(node, table: dict[str, Param]) -> dict:
    """Declare every parameter of ``table`` on ``node``; return name → validated value."""
    values = {}
    for name, p in table.items():
        value = node.declare_parameter(name, p.default, p.descriptor()).value
        values[name] = check(name, p, value)
    return values


def install_set_callback(node, table: dict[str, Param], apply=None) -> None:
    """Reject ``ros2 param set`` of a refused value; call ``apply(name, value)`` otherwise."""

    def on_set(params):
        for prm in params:
            if prm.name not in table:
                continue
            try:
                check(prm.name, table[prm.name], prm.value)
            except (ParameterError, TypeError, ValueError) as exc:
                return SetParametersResult(successful=False, reason=str(exc))
        if apply is not None:
            for prm in params:
                if prm.name in table:
                    apply(prm.name, prm.value)
        return SetParametersResult(successful=True)

    node.add_on_set_parameters_callback(on_set)


def _sigterm_as_interrupt(signum, frame):
    raise KeyboardInterrupt


def run(node_factory, name: str, args=None) -> None:
    """``main()`` of a node, shaped like ros2/demos' talker (jazzy): spin until Ctrl-C or
    an external shutdown, then ``destroy_node()`` and ``rclpy.try_shutdown()``. A refused
    parameter ends the process with a one-line message and exit code 2.

    rclpy's own SIGINT handler is disabled (SIGTERM is mapped to the same path) so the
    context is still valid in the node's ``on_shutdown()``: the servo's last word is a zero
    twist."""
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    signal.signal(signal.SIGTERM, _sigterm_as_interrupt)
    try:
        node = node_factory()
    except (ParameterError, InvalidParameterValueException, InvalidParameterTypeException,
            ValueError, TypeError, FileNotFoundError, ImportError) as exc:
        print(f'[{name}] refused to start: {exc}', file=sys.stderr)
        rclpy.try_shutdown()
        sys.exit(2)
    try:
        executor = rclpy.executors.SingleThreadedExecutor()
        executor.add_node(node)
        while rclpy.ok():  # wake up regularly so a pending KeyboardInterrupt is raised
            executor.spin_once(timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        on_exit = getattr(node, 'on_shutdown', None)
        if on_exit is not None:
            on_exit()
        node.destroy_node()
        rclpy.try_shutdown()
