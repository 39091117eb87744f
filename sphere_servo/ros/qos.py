"""
The QoS of every topic of the pipeline, in one place (the README's topic table lists them).

Every topic is reliable: in lockstep exactly one image is in flight and the loop needs each
image, measurement, features message and twist (a lost one holds the arm still until the
servo's watchdog); on one host, with the shipped Fast DDS profile, reliability costs an
acknowledgement, not a retransmission. Keep-last everywhere; the depth is what a topic
carries:

- :data:`SENSOR` (``camera/image_raw``, ``camera/camera_info``, ``detector/overlay``):
  depth 5. A reader that falls behind takes the newest frames, not a backlog of stale ones
  (5 frames: 83 ms at 60 Hz of slack for a reader the scheduler holds back). Best effort
  would save nothing here and would lose the image lockstep waits for.
  The camera's writer keeps more (:data:`WRITERS`: 30 images, 100 camera_infos, a second
  at 30 Hz): a reliable writer drops for a reader what leaves its history, and a recorder
  the scheduler holds back must still get every frame; each reader's own depth stays 5.
- :data:`COMMAND` (``camera/cmd_vel``): depth 10; the arm executes the newest.
- :data:`PIPELINE` (``detector/measurement``, ``features/<set>``): depth 10, per frame.
- :data:`MONITOR` (``~/state``, ``joint_states``, ``ground_truth/camera_pose``): depth
  100. Their readers are monitors (the launcher's supervisor, a recorder, a plot) that may
  fall behind on a loaded machine: a reliable writer drops for a reader what leaves its
  history, and the supervisor must see the first ``converged`` state.
- :data:`DIAGNOSTICS` (``/diagnostics``): depth 10, as diagnostic_updater publishes.
- :data:`CLOCK` (``/clock``): depth 10 (rclpy's time source subscribes best effort, which
  a reliable writer serves).
- :data:`LATCHED` (``features/<set>/desired``, ``/servo/enabled``, ``arm_sim/markers``):
  transient-local, depth 1: a late subscriber gets the last desired, the servo's mode (arm_sim
  refuses jumps while it is enabled) and the whole 3-D scene.

:func:`observer` gives a subscription that matches a topic's publishers with a history of
its own (the supervisor, tests): the same reliability and durability, another depth.

The writers (:data:`WRITERS`, :func:`writer`) of every stream but ``/clock`` and
``/diagnostics`` are transient-local with the table's depth or more: a recorder matched late
still gets what they sent; the table's readers are volatile and get only new messages.
"""
from __future__ import annotations

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy


def _reliable(depth: int, latched: bool = False) -> QoSProfile:
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=(DurabilityPolicy.TRANSIENT_LOCAL if latched
                                  else DurabilityPolicy.VOLATILE))


SENSOR = _reliable(5)
COMMAND = _reliable(10)
PIPELINE = _reliable(10)
MONITOR = _reliable(100)
DIAGNOSTICS = _reliable(10)
CLOCK = _reliable(10)
LATCHED = _reliable(1, latched=True)

# topic (relative name; ``<node>/state`` for ``~/state``) → its QoS
TOPICS = {
    'camera/image_raw': SENSOR,
    'camera/camera_info': SENSOR,
    'detector/overlay': SENSOR,
    'camera/cmd_vel': COMMAND,
    'detector/measurement': PIPELINE,
    'features/<set>': PIPELINE,
    'features/<set>/desired': LATCHED,
    '/servo/enabled': LATCHED,
    'arm_sim/markers': LATCHED,
    'joint_states': MONITOR,
    'ground_truth/camera_pose': MONITOR,
    '<node>/state': MONITOR,
    '/diagnostics': DIAGNOSTICS,
    '/clock': CLOCK,
}


# a stream's writer: transient-local, so that a recorder that adapts to it (ours, rosbag2's)
# gets on matching what was sent before: under load a writer matches a new reader up to a
# discovery heartbeat (seconds) after that reader already reports itself matched. The
# table's readers stay volatile: a node never gets stale frames. The camera keeps more (the
# scheduler may hold a recorder back for a second at 30 Hz).
_DEEPER = {'camera/image_raw': 30, 'camera/camera_info': 100}
WRITERS = {topic: _reliable(_DEEPER.get(topic, reader.depth), latched=True)
           for topic, reader in TOPICS.items()
           if reader.durability == DurabilityPolicy.VOLATILE
           and topic not in ('/clock', '/diagnostics')}


def writer(topic: str) -> QoSProfile:
    """Return the profile the publisher of ``topic`` (a key of :data:`TOPICS`) offers."""
    return WRITERS.get(topic, TOPICS[topic])


def observer(profile: QoSProfile, depth: int = 1000) -> QoSProfile:
    """Return a subscription QoS that matches ``profile``'s publishers, keep-last ``depth``."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                      reliability=profile.reliability, durability=profile.durability)


def best_effort(profile: QoSProfile) -> QoSProfile:
    """
    Return ``profile`` as a best-effort reader: it matches best-effort writers too.

    For a camera that publishes best effort (``SensorDataQoS``), which a reliable reader
    never matches (the detector's and the features node's ``image_reliability``).
    """
    return QoSProfile(history=profile.history, depth=profile.depth,
                      reliability=ReliabilityPolicy.BEST_EFFORT, durability=profile.durability)


def camera_reader(node, reliability: str, log):
    """
    Return ``(qos, event_callbacks)`` of a node's readers of the camera's topics.

    ``reliability`` is the node's ``image_reliability``: 'reliable' (:data:`SENSOR`) or
    'best_effort' (:func:`best_effort`). A camera publisher no reader of that QoS can match
    is logged through ``log`` (a :class:`~sphere_servo.ros.logs.ThrottledLog`) with the fix,
    instead of rclpy's bare warning.
    """
    from rclpy.event_handler import SubscriptionEventCallbacks
    from rclpy.qos import qos_policy_name_from_kind

    def incompatible(event) -> None:
        policy = qos_policy_name_from_kind(event.last_policy_kind)
        log.warn(f'a camera publisher offers QoS this reader cannot match ({policy}): '
                 'nothing of it is received' + (
                     '; a best-effort camera? set image_reliability: best_effort'
                     if policy == 'RELIABILITY' else ''))
    qos = SENSOR if reliability == 'reliable' else best_effort(SENSOR)
    return qos, SubscriptionEventCallbacks(incompatible_qos=incompatible)
