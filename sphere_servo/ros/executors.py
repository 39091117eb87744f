"""
The executor the nodes spin on: rclpy's EventsExecutor where this rclpy has it.

rclpy's ``SingleThreadedExecutor`` rebuilds a wait set of every subscription, timer,
service and client of its nodes in Python before each wait; with the parameter services
every node has, that is about a millisecond per wait on this machine, paid again at each
hop of the pipeline (four nodes in one process: four times the entities). The
``EventsExecutor`` (``rclpy.experimental``, in Jazzy since rclpy 7.1) is driven by the
middleware's callbacks and keeps its queue in C++: measured side by side on this machine,
the pipeline's image stamp → twist publish went from 12.6–15.3 ms to 8.2–9.1 ms in three
processes and from 10.9 ms to 6.2–7.3 ms in one (both under the machine's other load). Both
run every callback on the spinning thread, one at a time.

The EventsExecutor calls a subscription's callback with the message only, never with its
``MessageInfo``: a process with a callback that takes it (:func:`wants_message_info`:
arm_sim, whose one-driver rule reads each command's publication sequence number) spins on
the ``SingleThreadedExecutor``. arm_sim is not on the image → twist path, so this costs the
three-process pipeline nothing; one process (``pipeline``) spins all four on it.

``SPHERE_SERVO_EXECUTOR=single_threaded`` selects rclpy's classic executor instead;
``events`` (the default) falls back to it, with a warning, where rclpy has no
EventsExecutor.
"""
from __future__ import annotations

import os
import sys

VARIABLE = 'SPHERE_SERVO_EXECUTOR'
CHOICES = ('events', 'single_threaded')


def executor_choice(env=None) -> str:
    """Return the executor ``env`` (default: this process's environment) selects."""
    choice = (os.environ if env is None else env).get(VARIABLE, '') or CHOICES[0]
    if choice not in CHOICES:
        raise ValueError(f'{VARIABLE}={choice!r}: use one of {CHOICES}')
    return choice


def wants_message_info(nodes) -> bool:
    """
    Whether a subscription of ``nodes`` has a callback that takes its ``MessageInfo``.

    That is rclpy's own decision from the callback's signature, made when the subscription
    is created; it has no public accessor.
    """
    from rclpy.subscription import Subscription
    info = Subscription.CallbackType.WithMessageInfo
    return any(getattr(sub, '_callback_type', None) is info
               for node in nodes for sub in node.subscriptions)


def make_executor(context=None, message_info: bool = False):
    """
    Return a new executor of :func:`executor_choice`'s kind on ``context``.

    ``message_info``: a callback needs its ``MessageInfo``, which only the
    ``SingleThreadedExecutor`` passes.
    """
    from rclpy.executors import SingleThreadedExecutor
    if executor_choice() == 'events' and not message_info:
        try:
            from rclpy.experimental.events_executor import EventsExecutor
        except ImportError:
            print('[sphere_servo] this rclpy has no EventsExecutor: using the '
                  'SingleThreadedExecutor', file=sys.stderr)
        else:
            return EventsExecutor(context=context)
    return SingleThreadedExecutor(context=context)
