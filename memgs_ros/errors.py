"""The package's error hierarchy: one base, one class per subpackage concern.

Foreign exceptions are translated at the boundary (``raise DataError(...) from err``)
with a message that names the file or message and the problem, so the CLI can print
one line instead of a traceback.
"""


class MemgsError(Exception):
    """Base class of every error memgs_ros raises on purpose."""


class DataError(MemgsError):
    """A dataset folder, bag, PLY or config file is missing, corrupt or inconsistent."""


class MessageError(MemgsError):
    """A ROS message cannot be converted (bad encoding, size mismatch, missing field)."""


class ConfigError(MemgsError):
    """A parameter value is out of range or inconsistent with another."""


class PipelineError(MemgsError):
    """A run of the node graph failed: a node died or timed out, or the run could not finish."""
