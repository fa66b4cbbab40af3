"""Project exceptions: every user-facing failure is one of these, with a message
that names the file or value at fault and how to fix it."""


class MitsubaP3Error(Exception):
    """Base class; the CLI prints its message as one line and exits non-zero."""


class BackendError(MitsubaP3Error):
    """No usable Dr.Jit/LLVM backend (missing or known-broken libLLVM)."""


class SceneError(MitsubaP3Error):
    """A scene description (XML or parameters) is malformed or out of range."""
