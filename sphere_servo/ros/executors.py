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
``MessageInfo``: a node with a callback that takes it (:func:`wants_message_info`: arm_sim,
whose one-driver rule reads each command's publication sequence number) spins on the
``SingleThreadedExecutor``. arm_sim is not on the image → twist path, so this costs the
three-process pipeline nothing. In one process (:class:`NodeExecutors`, the
``pipeline`` executable of ``launcher --single-process``) arm_sim's classic executor spins
on a thread of its own and the other nodes share the EventsExecutor on the main thread:
all four on the classic executor, each hop of the image → twist path paid the wait set of
four nodes' entities (image stamp → twist publish 8.9–9.4 ms there against 6.2–6.5 ms,
measured side by side under a helper's load). Both executors wait without the GIL; the
callbacks of one node still run one at a time, on its executor's thread.

``SPHERE_SERVO_EXECUTOR=single_threaded`` selects rclpy's classic executor instead;
``events`` (the default) falls back to it, with a warning, where rclpy has no
EventsExecutor.
"""
from __future__ import annotations

import os
import sys
import threading

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


def executor_groups(nodes) -> list[tuple[bool, list]]:
    """
    Return ``[(message_info, nodes), ...]``: ``nodes`` split among the executors they need.

    Under :func:`executor_choice` ``events``, the nodes whose callbacks read their
    ``MessageInfo`` form a group apart (``True``) from the others (``False``); under
    ``single_threaded``, one group (the classic executor passes it to all). Order kept.
    """
    if executor_choice() == 'single_threaded':
        return [(wants_message_info(nodes), list(nodes))]
    groups: dict[bool, list] = {}
    if not nodes:
        return [(False, [])]
    for node in nodes:
        groups.setdefault(wants_message_info([node]), []).append(node)
    return sorted(groups.items(), key=lambda g: g[0])


class NodeExecutors:
    """
    The executors of a process's nodes (:func:`executor_groups`), spun as one.

    The first group spins on the caller's thread (:meth:`spin_once`), any other on a
    thread of its own from :meth:`start` until :meth:`stop_threads`; an exception that ends
    such a thread is raised again by the next :meth:`spin_once`, so the process does not
    run on without those nodes.
    """

    def __init__(self, nodes, context=None):
        self.executors = []
        for message_info, group in executor_groups(nodes):
            executor = make_executor(context, message_info=message_info)
            for node in group:
                executor.add_node(node)
            self.executors.append((executor, group))
        self._threads: list[threading.Thread] = []
        self._stopping = threading.Event()
        self.failed: BaseException | None = None

    def threaded(self, node) -> bool:
        """Whether ``node`` spins on a thread of its own executor, not the caller's."""
        return any(node in group for _, group in self.executors[1:])

    def start(self) -> None:
        """Start the threads of the executors after the first."""
        for executor, _ in self.executors[1:]:
            thread = threading.Thread(target=self._spin, args=(executor,), daemon=True,
                                      name=f'spin {type(executor).__name__}')
            thread.start()
            self._threads.append(thread)

    def _spin(self, executor) -> None:
        from rclpy.executors import ExternalShutdownException
        try:
            while not self._stopping.is_set():
                executor.spin_once(timeout_sec=0.1)
        except ExternalShutdownException:
            pass
        except Exception as exc:  # handed to the main thread, raised there
            self.failed = exc

    def spin_once(self, timeout_sec: float) -> None:
        """Spin the first executor once; raise what ended another's thread, if anything."""
        if self.failed is not None:
            raise self.failed
        self.executors[0][0].spin_once(timeout_sec=timeout_sec)

    def stop_threads(self, timeout: float = 5.0) -> None:
        """Stop the other executors' threads (their nodes' callbacks no longer run)."""
        self._stopping.set()
        for thread in self._threads:
            thread.join(timeout)
        self._threads.clear()
