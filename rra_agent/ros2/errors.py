"""Errors of the ROS 2 layer: each a one-line `RraError` saying what and where."""

from __future__ import annotations

from rra_agent.errors import RraError


class Ros2Error(RraError):
    """Root of the ROS 2 layer's errors."""


class BadName(Ros2Error):
    """A ROS 2 topic, service, node or type name that is not valid."""


class BadToken(Ros2Error):
    """A liveliness token or data key that does not follow rmw_zenoh's format."""


class BadAttachment(Ros2Error):
    """An attachment that is not rmw_zenoh's (sequence number, timestamp, GID)."""


class UnknownType(Ros2Error):
    """A message or service type the registry does not know."""


class FieldError(Ros2Error):
    """A dotted field path or a field value that does not fit the message type."""


class DecodeError(Ros2Error):
    """Bytes that are not a CDR encoding of the expected type."""


class ServiceTimeout(Ros2Error):
    """A service call that got no reply before its deadline."""


class ServiceFailed(Ros2Error):
    """A service call that got an error reply or a reply that could not be decoded."""


class NoServer(ServiceFailed):
    """A service call that reached no server: it ended at once, without any reply (a server
    that has just appeared may not be reached for a moment yet)."""
