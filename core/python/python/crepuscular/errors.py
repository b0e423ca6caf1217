"""The exceptions crepuscular raises.

    CrepuscularError(Exception)
    ├── InvalidInputError(CrepuscularError, ValueError)  an unusable value; `field` names it
    ├── ExrError(CrepuscularError, OSError)              reading or writing a file failed
    └── CancelledError(CrepuscularError)                 the render was cancelled

They are defined in the native module and re-exported here and from `crepuscular`.
"""

from crepuscular._core import CancelledError, CrepuscularError, ExrError, InvalidInputError

__all__ = ["CancelledError", "CrepuscularError", "ExrError", "InvalidInputError"]
