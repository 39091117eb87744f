"""
The last line of defence of a node's callbacks: log, go safe, keep running.

Inputs are validated in the ROS-free cores, so a callback has no exception to expect; one
that still escapes (a bug, an input nobody thought of) would end the node (rclpy's executor
re-raises it), leaving the arm with its last command. :func:`guarded` wraps a subscription
or timer callback: the exception is logged (throttled, with its type) and the node's
``go_safe()`` runs (the servo sends a zero twist, arm_sim stops the arm, the detector and
the features publish their empty "target lost" answer). :func:`guarded_service` wraps a
``std_srvs`` service callback: the reply is a failure naming the exception.

The wrappers keep the callback's signature (``functools.wraps``), which rclpy reads to tell
a callback that takes the message info from one that does not.
"""
from __future__ import annotations

import functools


def _report(node, fn, exc: BaseException) -> None:
    node.get_logger().error(
        f'{fn.__name__} failed, going safe (a bug: please report it): '
        f'{type(exc).__name__}: {exc}', throttle_duration_sec=1.0)


def _wrap(fn, fail):
    """Wrap a callback method: an exception is reported, then ``fail(self, args, exc)``."""
    @functools.wraps(fn)
    def wrapper(self, *args):
        try:
            return fn(self, *args)
        except Exception as exc:  # noqa: BLE001 - the guard of last resort
            _report(self, fn, exc)
            return fail(self, args, exc)
    return wrapper


def _go_safe(node, args, exc):
    try:
        node.go_safe(*args)
    except Exception as again:  # noqa: BLE001 - never raise out of a callback
        _report(node, node.go_safe, again)


def _failed(node, args, exc):
    response = args[-1]
    response.success = False
    response.message = f'failed: {type(exc).__name__}: {exc}'
    return response


def guarded(fn):
    """Wrap a callback method: an exception is logged and ``self.go_safe(*args)`` runs."""
    return _wrap(fn, _go_safe)


def guarded_service(fn):
    """
    Wrap a service callback method ``(…, request, response)``: an exception is a failure.

    The response is the last argument; its ``success`` and ``message`` say what failed.
    """
    return _wrap(fn, _failed)
