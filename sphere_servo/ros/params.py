"""
Parameters declared from a node's table, and the ``main()`` shape shared by the nodes.

:func:`declare_all` declares every entry of a :class:`~sphere_servo.pipeline.params.NodeParams`
dataclass's table with a ``ParameterDescriptor`` (description, ranges) and returns the
validated dataclass; a refused value raises :class:`ParameterError` at start, and a later
``ros2 param set`` of a refused value is rejected by :func:`install_set_callback`.

:func:`run` is ros2/demos' talker (jazzy) with one change: SIGINT and SIGTERM only set a stop
flag that the spin loop checks. A ``KeyboardInterrupt`` raised asynchronously can land
anywhere, also inside rclpy's ``take_message`` (Python called from C++), where pybind turns
it into a ``RuntimeError`` and the node dies with exit code 1.
"""
from __future__ import annotations

import signal
import sys

from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                SetParametersResult)
import rclpy
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.executors import ExternalShutdownException
from rclpy.signals import SignalHandlerOptions
from sphere_servo.pipeline.params import NodeParams, Param, ParameterError
from sphere_servo.ros.executors import make_executor


def descriptor(p: Param) -> ParameterDescriptor:
    """Return the ``ParameterDescriptor`` of a parameter (description, constraints)."""
    d = ParameterDescriptor(description=p.description, read_only=p.read_only)
    if p.choices:
        d.additional_constraints = f'one of {list(p.choices)}'
    if p.size:
        d.additional_constraints = f'{p.size} finite numbers'
    if p.bounds is not None:
        lo, hi = p.bounds
        if isinstance(p.default, bool):
            pass
        elif isinstance(p.default, int):
            d.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=1)]
        elif isinstance(p.default, float):
            d.floating_point_range = [FloatingPointRange(from_value=float(lo),
                                                         to_value=float(hi), step=0.0)]
    return d


def declare_all(node, cls: type[NodeParams]) -> NodeParams:
    """Declare every parameter of ``cls`` on ``node``; return the validated parameters."""
    return cls.from_mapping({name: node.declare_parameter(name, p.default, descriptor(p)).value
                             for name, p in cls.table().items()})


def install_set_callback(node, get, apply) -> None:
    """
    Reject ``ros2 param set`` of a refused value; otherwise ``apply`` the new parameters.

    ``get()`` returns the node's current parameters; ``apply(new)`` receives them with the
    change, validated as at start (the cross-parameter rules included).
    """
    table = get().table()

    def on_set(params):
        changes = {prm.name: prm.value for prm in params if prm.name in table}
        if changes:
            try:
                new = get().replace(changes)
            except (ParameterError, TypeError, ValueError) as exc:
                return SetParametersResult(successful=False, reason=str(exc))
            apply(new)
        return SetParametersResult(successful=True)

    node.add_on_set_parameters_callback(on_set)


class StopFlag:
    """Set by SIGINT and SIGTERM; the spin loop ends when it is."""

    def __init__(self):
        self.requested = False

    def __call__(self, signum, frame) -> None:
        """Record the request (a signal handler: nothing else, nothing raised)."""
        self.requested = True

    @classmethod
    def install(cls) -> StopFlag:
        """Return a flag that SIGINT and SIGTERM set from now on."""
        flag = cls()
        signal.signal(signal.SIGINT, flag)
        signal.signal(signal.SIGTERM, flag)
        return flag


def run(node_factory, name: str, args=None) -> None:
    """
    Run the node, or list of nodes, that ``node_factory`` returns until Ctrl-C or SIGTERM.

    An external shutdown ends it too. Then ``on_shutdown()`` (if the node has one: the
    servo's last word is a zero twist), ``destroy_node()`` and ``rclpy.try_shutdown()``;
    several nodes share one executor and are shut down in the list's order. rclpy's own
    signal handler is disabled so the context is still valid in ``on_shutdown()``. A refused
    parameter ends the process with a one-line message and exit code 2.
    """
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    stop = StopFlag.install()
    try:
        made = node_factory()
        nodes = list(made) if isinstance(made, (list, tuple)) else [made]
    except (ParameterError, InvalidParameterValueException, InvalidParameterTypeException,
            ValueError, TypeError, FileNotFoundError, ImportError) as exc:
        print(f'[{name}] refused to start: {exc}', file=sys.stderr)
        rclpy.try_shutdown()
        sys.exit(2)
    try:
        executor = make_executor()
        for node in nodes:
            executor.add_node(node)
        while rclpy.ok() and not stop.requested:  # the timeout bounds the reaction time
            executor.spin_once(timeout_sec=0.1)
    except ExternalShutdownException:
        pass
    finally:
        for node in nodes:
            on_exit = getattr(node, 'on_shutdown', None)
            if on_exit is not None:
                on_exit()
        for node in nodes:
            node.destroy_node()
        rclpy.try_shutdown()
