"""The one exception tree of dh2rt.

Every error dh2rt raises derives from :class:`DH2Error` and is grouped by the phase in which
it arises. Each class also inherits the builtin that fits it, so callers that already catch
``ValueError`` or ``OSError`` keep working::

    DH2Error
    ├── ProgramError (ValueError)           a DH2 program is wrong; carries file:line:col
    │   ├── ProgramSyntaxError              the text does not parse
    │   └── ProgramCompileError             it parses but means nothing valid
    ├── TopologyError (ValueError)          a topology spec or file is wrong
    ├── HormoneError (ValueError)           a hormone breaks a limit (too long, bad value)
    ├── ImageError (ValueError)             a serialized program image is corrupt or foreign
    ├── CodecError (ValueError)             bytes on a link do not decode
    │   └── FrameCorrupted                  a frame failed its CRC or framing
    ├── TransportError (OSError)            a link or bus is missing or failed
    │   └── TransportUnavailable            the interface does not exist on this machine
    ├── DriverError (RuntimeError)          a servo or its stand-in failed
    │   ├── ServoNotFound                   no reply from the servo id
    │   ├── ServoModelMismatch              a servo answered with the wrong model number
    │   ├── ServoCommError                  a packet was lost or garbled (CRC, timeout)
    │   └── ServoHardwareAlert              the servo reports a hardware error
    ├── SimulationError (RuntimeError)      the physics stand-in failed
    └── OutputError (ValueError)            an output option names a file that cannot be written
"""

from __future__ import annotations

from dataclasses import dataclass


class DH2Error(Exception):
    """Root of every error dh2rt raises."""


@dataclass(frozen=True, slots=True)
class SourceSpan:
    """A place in a program's text: 1-based line and column."""

    file: str
    line: int
    column: int
    source_line: str = ""

    def __str__(self) -> str:
        return f"{self.file}:{self.line}:{self.column}"


class ProgramError(DH2Error, ValueError):
    """A DH2 program is wrong. ``str()`` gives ``FILE:LINE:COL: message`` plus a caret."""

    def __init__(self, message: str, span: SourceSpan | None = None) -> None:
        self.message = message
        self.span = span
        super().__init__(self.render())

    def render(self) -> str:
        if self.span is None:
            return self.message
        text = f"{self.span}: {self.message}"
        if self.span.source_line:
            line, column = _window(self.span.source_line, self.span.column)
            caret = " " * (column - 1) + "^"
            text += f"\n    {line}\n    {caret}"
        return text


#: Source lines longer than this are shown as a window around the column.
SHOWN_LINE = 100


def _window(line: str, column: int) -> tuple[str, int]:
    """The part of ``line`` to show around ``column`` (1-based), and the column in it."""
    if len(line) <= SHOWN_LINE:
        return line, column
    start = max(0, min(column - 1 - SHOWN_LINE // 2, len(line) - SHOWN_LINE))
    end = start + SHOWN_LINE
    shown = ("..." if start else "") + line[start:end] + ("..." if end < len(line) else "")
    return shown, column - start + (3 if start else 0)


class ProgramSyntaxError(ProgramError):
    """The program text does not parse."""


class ProgramCompileError(ProgramError):
    """The program parses but refers to unknown names, breaks arity or limits."""


class TopologyError(DH2Error, ValueError):
    """A topology spec or file is wrong."""


class HormoneError(DH2Error, ValueError):
    """A hormone breaks a limit (content too long, value out of range)."""


class ImageError(DH2Error, ValueError):
    """A serialized program image is corrupt, truncated or of another format version."""


class CodecError(DH2Error, ValueError):
    """Bytes received on a link do not decode to a frame."""


class FrameCorrupted(CodecError):
    """A frame failed its CRC or its framing."""


class TransportError(DH2Error, OSError):
    """A link, port or bus failed."""


class TransportUnavailable(TransportError):
    """The requested interface does not exist on this machine."""


class DriverError(DH2Error, RuntimeError):
    """A servo or its stand-in failed."""


class ServoNotFound(DriverError):
    """No reply from a servo id."""


class ServoModelMismatch(DriverError):
    """A servo answered with an unexpected model number."""


class ServoCommError(DriverError):
    """A packet to or from a servo was lost or garbled."""


class ServoHardwareAlert(DriverError):
    """A servo reports a hardware error (overload, overheating, voltage)."""


class SimulationError(DH2Error, RuntimeError):
    """The physics stand-in failed."""


class OutputError(DH2Error, ValueError):
    """An output option names a file that cannot be written as asked (exit 2)."""
