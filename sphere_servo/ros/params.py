"""
Parameters declared from a node's table, and the ``main()`` shape shared by the nodes.

:func:`declare_all` declares every entry of a :class:`~sphere_servo.pipeline.params.NodeParams`
dataclass's table with a ``ParameterDescriptor`` (description, ranges) and returns the
validated dataclass; a refused value raises :class:`ParameterError` at start, and a later
``ros2 param set`` of a refused value is rejected by :func:`install_set_callback`.

:func:`run` is ros2/demos' talker (jazzy) with two changes. SIGINT and SIGTERM only set a
stop flag that the spin loop checks: a ``KeyboardInterrupt`` raised asynchronously can land
anywhere, also inside rclpy's ``take_message`` (Python called from C++), where pybind turns
it into a ``RuntimeError`` and the node dies with exit code 1. And the objects of the
start-up are frozen (:func:`freeze_startup`) before the first callback.
"""
from __future__ import annotations

import gc
import os
from pathlib import Path
import signal
import sys

from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                SetParametersResult)
import rclpy
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.executors import ExternalShutdownException
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.signals import SignalHandlerOptions
from sphere_servo.pipeline.allocator import keep_heap
from sphere_servo.pipeline.config import ConfigError, read_yaml
from sphere_servo.pipeline.middleware import environment_problem
from sphere_servo.pipeline.params import (check_names, NodeParams, Param, ParameterError,
                                          ROS_PARAMETERS)
from sphere_servo.ros.executors import NodeExecutors


def descriptor(p: Param) -> ParameterDescriptor:
    """Return the ``ParameterDescriptor`` of a parameter (description, constraints)."""
    d = ParameterDescriptor(description=p.description, read_only=p.read_only)
    if p.choices:
        d.additional_constraints = f'one of {list(p.choices)}'
    if p.size:
        d.additional_constraints = f'{p.size} finite numbers' + (
            f', each within {list(p.bounds)}' if p.bounds is not None else '')
    if p.bounds is not None and not p.size:
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
    """
    Declare every parameter of ``cls`` on ``node``; return the validated parameters.

    A parameter given that is not declared (:func:`check_overrides`) is refused first;
    ``qos_overrides.*`` are declared by rclpy with the publishers, and checked by
    :func:`run` once the node is built.
    """
    values = {name: node.declare_parameter(name, p.default, descriptor(p)).value
              for name, p in cls.table().items()}
    check_overrides(node, skip=('qos_overrides.',))
    return cls.from_mapping(values)


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


def params_files(args) -> list[str]:
    """Return the ``--params-file`` paths of a command line, in its ``--ros-args`` parts."""
    files, ros = [], False
    args = list(args)
    for i, a in enumerate(args):
        if a == '--ros-args':
            ros = True
        elif a == '--':
            ros = False
        elif ros and a == '--params-file' and i + 1 < len(args):
            files.append(args[i + 1])
    return files


def check_params_files(args) -> None:
    """Refuse (ConfigError, one line) a ``--params-file`` that is missing or not a mapping."""
    for f in params_files(args):
        if not Path(f).is_file():
            raise ConfigError(f'--params-file {f!r} does not exist or is not a file')
        read_yaml(Path(f))


def check_overrides(node, skip: tuple[str, ...] = ()) -> None:
    """
    Refuse parameters given to ``node`` that it does not declare (ParameterError).

    rclpy keeps every override of the command line and the params files in the node's
    ``_parameter_overrides`` (no public accessor) and ignores those never declared.
    Names starting with a prefix in ``skip`` are not checked.
    """
    given = [n for n in node._parameter_overrides if not n.startswith(skip)]
    if all(node.has_parameter(n) for n in given):
        return
    names = node.list_parameters([], 0).names
    check_names(given, [n for n in names if n not in ROS_PARAMETERS],
                [n for n in names if n in ROS_PARAMETERS])


def freeze_startup() -> None:
    """
    Take the objects alive now out of the garbage collector's full collections (``gc.freeze``).

    A node's start-up leaves tens of thousands of objects that live as long as it does
    (modules, rclpy, Pinocchio's model, the renderer); every full (generation-2) collection
    walks them all, inside whichever callback allocated last: 50 to 120 ms in each node on
    this machine under two busy processes, a stall on the lockstep loop's path. Frozen, a full
    collection walks only what was made since. The garbage of the start-up is collected
    first, so that none of it is kept for good.
    """
    gc.collect()
    gc.freeze()


def _refuse(name: str, exc) -> None:
    text = ' '.join(str(exc).split())  # one line: YAML and rcl errors span several
    print(f'[{name}] refused to start: {text}', file=sys.stderr)
    rclpy.try_shutdown()
    sys.exit(2)


def run(node_factory, name: str, args=None) -> None:
    """
    Run the node, or list of nodes, that ``node_factory`` returns until Ctrl-C or SIGTERM.

    An external shutdown ends it too. Then ``on_shutdown()`` (if the node has one: the
    servo's last word is a zero twist), ``destroy_node()`` and ``rclpy.try_shutdown()``;
    several nodes are spun by :class:`~sphere_servo.ros.executors.NodeExecutors` (one
    executor; with arm_sim among others, its own on a thread) and shut down in the list's
    order. rclpy's own signal handler is disabled so the context is still valid in
    ``on_shutdown()``. The start-up's objects are frozen before the first spin
    (:func:`freeze_startup`); image-sized blocks stay in the C heap between messages
    (:func:`~sphere_servo.pipeline.allocator.keep_heap`). An environment no node can work with
    (:func:`~sphere_servo.pipeline.middleware.environment_problem`), a bad params file, a
    refused or an undeclared parameter end the process with a one-line message and exit
    code 2.
    """
    keep_heap()
    try:
        problem = environment_problem(os.environ)
        if problem is not None:
            raise ConfigError(problem)
        check_params_files(sys.argv if args is None else args)
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    except (ConfigError, _rclpy.RCLError) as exc:
        _refuse(name, str(exc).split(', at /')[0])  # rcl appends its source locations
    stop = StopFlag.install()
    try:
        made = node_factory()
        nodes = list(made) if isinstance(made, (list, tuple)) else [made]
        for node in nodes:
            check_overrides(node)
    except (ParameterError, InvalidParameterValueException, InvalidParameterTypeException,
            ValueError, TypeError, FileNotFoundError, ImportError, ConfigError) as exc:
        _refuse(name, exc)
    executors = None
    try:
        executors = NodeExecutors(nodes)
        freeze_startup()
        executors.start()
        while rclpy.ok() and not stop.requested:  # the timeout bounds the reaction time
            executors.spin_once(timeout_sec=0.1)
    except ExternalShutdownException:
        pass
    finally:
        for node in nodes:
            if executors is not None and executors.threaded(node):
                executors.stop_threads()  # its callbacks must not run beside on_shutdown
            on_exit = getattr(node, 'on_shutdown', None)
            if on_exit is not None:
                on_exit()
        for node in nodes:
            node.destroy_node()
        rclpy.try_shutdown()
