"""
``pipeline``: the pipeline's nodes in one process (``launcher --single-process``).

    pipeline [arm_sim detector features servo] --ros-args --params-file A --params-file B

The rclpy counterpart of component composition: the node classes of ``arm_sim``,
``detector``, ``features`` and ``servo`` (:mod:`sphere_servo.ros`) are constructed in this
process and spun there (:func:`sphere_servo.ros.params.run`): detector, features and servo
on one EventsExecutor, arm_sim (its command callback reads its MessageInfo, which that
executor does not pass) on a classic executor on a thread of its own, as
``component_container_isolated`` gives a component its own
(:class:`~sphere_servo.ros.executors.NodeExecutors`). A message between them never leaves
the process: Fast DDS hands it from writer to reader inside the one participant the process
has, without a transport. Each node takes its own
section of the params files, as when it runs alone; names, topics, services, parameters and
QoS are the same as in separate processes.

The consumers are constructed first (servo, features, detector, then arm_sim), so the
arm's first frame finds its readers, and shut down in that order: the servo's last word is
a zero twist while the arm still listens. A refused parameter of any node ends the process
with exit code 2, as one node alone does; an unknown node name, or one given twice, too.
"""
from __future__ import annotations

import importlib
import sys

# node name → (module, class); the order is the construction and shutdown order
NODE_CLASSES = {'servo': ('sphere_servo.ros.servo', 'ServoNode'),
                'features': ('sphere_servo.ros.features', 'FeaturesNode'),
                'detector': ('sphere_servo.ros.detector', 'DetectorNode'),
                'arm_sim': ('sphere_servo.ros.arm_sim', 'ArmSim')}


def node_classes(names) -> list[type]:
    """Return the node classes of ``names``, consumers first; ValueError: unknown or twice."""
    unknown = [n for n in names if n not in NODE_CLASSES]
    twice = sorted({n for n in names if list(names).count(n) > 1})
    if twice:
        raise ValueError(f'node(s) {twice} named twice: one process holds one node of a name')
    if unknown:
        raise ValueError(f'unknown node(s) {unknown}: the pipeline composes '
                         f'{sorted(NODE_CLASSES)}')
    return [getattr(importlib.import_module(module), cls)
            for name, (module, cls) in NODE_CLASSES.items() if name in names]


def main(args=None) -> None:
    """Run the nodes named before ``--ros-args`` (default: all four) in this process."""
    from rclpy.utilities import remove_ros_args
    from sphere_servo.ros.params import run
    argv = list(sys.argv if args is None else args)
    names = remove_ros_args(argv)[1:] or list(NODE_CLASSES)
    try:
        classes = node_classes(names)
    except ValueError as exc:
        print(f'[pipeline] refused to start: {exc}', file=sys.stderr)
        sys.exit(2)
    run(lambda: [cls() for cls in classes], 'pipeline', argv)


if __name__ == '__main__':
    main()
