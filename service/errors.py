"""Domain errors, each naming the field, file or key at fault; adapters map them to exit codes or HTTP codes."""


class SeasynthError(Exception):
    """Base of every error the product raises on purpose."""


class SpecError(SeasynthError, ValueError):
    """An invalid dataset spec; the message names each bad field."""


class AssetError(SeasynthError, ValueError):
    """A mesh or texture that cannot be used; the message names the file."""


class OutputError(SeasynthError):
    """An output folder or object that cannot be written; the message names it."""


class ExportError(SeasynthError):
    """A dataset that cannot be exported as asked (missing, incomplete or inconsistent files, a bad split) or an
    export folder that cannot be written; the message names the file, frame or option at fault."""


class ParameterError(SeasynthError, ValueError):
    """A request's parameters ask for more than can be served (e.g. a preview sheet too large to draw); the message
    names the parameters."""


class RenderError(SeasynthError):
    """The renderer could not start or render; the message says which backend and why."""


class NotFound(SeasynthError, KeyError):
    """A dataset, asset or frame that does not exist."""

    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0]) if self.args else ""


class Conflict(SeasynthError):
    """A request that conflicts with the current state (e.g. cancelling a finished dataset's frames)."""


class LimitExceeded(SeasynthError, ValueError):
    """A request over a configured limit; the message names the limit."""


class Unavailable(SeasynthError):
    """A dependency (Redis, the bucket, a frame worker) did not answer in time; the client may retry later."""


class Unreachable(Unavailable):
    """A dependency could not be reached at all (connection refused, reset or timed out) or answered 5xx: an outage,
    not a fault of the request, so a shard it interrupts is retried without using up its attempts."""


class Unauthorized(SeasynthError):
    """A request without a valid API key."""


class CalibrationError(SeasynthError, ValueError):
    """A photo or range map the water cannot be estimated from; the message names the input and why."""
