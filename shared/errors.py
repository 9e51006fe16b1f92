"""Domain errors, shared by the core, the CLI and the services.

Each service maps these to HTTP answers in one exception handler; the CLI prints them.
"""


class FleetmapError(Exception):
    """Base class of every error fleetmap raises on purpose."""


class BadInput(FleetmapError, ValueError):
    """Input of the wrong shape, type, size or value."""


class NoDepthReading(BadInput):
    """A depth image without a single reading (a sensor warming up, a covered lens)."""


class BadFrame(BadInput):
    """An encoded frame structure that cannot be decoded or fails validation."""


class BadRobotData(FleetmapError):
    """A robot folder that is missing, incomplete or unreadable."""


class BadVocabulary(FleetmapError):
    """A vocabulary file that is missing, of another format version or inconsistent."""


class UnknownRobot(FleetmapError, KeyError):
    """A robot id the place database does not know."""

    def __str__(self) -> str:  # KeyError quotes its message; keep it plain
        return str(self.args[0]) if self.args else "unknown robot"


class UnknownKeyframe(FleetmapError, KeyError):
    """A keyframe id the place database does not know."""

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else "unknown keyframe"


class UnknownCloud(UnknownKeyframe):
    """A merged cloud id the aligner does not hold (never made, or gone from its cache)."""


class NotSolved(FleetmapError, LookupError):
    """Something the live map has not computed (yet) for its current placement."""


class NotEnoughCorrespondences(FleetmapError):
    """Too few (inlier) correspondences to fit or verify a transform."""


class PayloadTooLarge(BadInput):
    """A body or field larger than the configured limit."""


class Conflict(FleetmapError):
    """A write that contradicts what is stored (e.g. another keyframe at the same stamp)."""


class Unavailable(FleetmapError):
    """A service or resource that cannot be reached or is not ready."""

    def __init__(self, message: str = "", retry_after: float | None = None):
        super().__init__(message)
        self.retry_after = retry_after


class RequestTimeout(BadInput):
    """A client stopped sending its request midway."""


class Unauthorized(FleetmapError):
    """No valid credentials."""


class Forbidden(FleetmapError):
    """Valid credentials that do not allow this action."""


class UnsupportedEncoding(BadInput):
    """A body in a content encoding the service does not accept (e.g. compressed)."""


class StorageCorrupt(FleetmapError):
    """Stored data failed its integrity check: the server's fault, never the client's."""


class MissingDependency(FleetmapError, ImportError):
    """A library of the `server` extra that this install lacks (a robot-side install)."""
