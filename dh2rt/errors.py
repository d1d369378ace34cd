"""The one exception tree of dh2rt.

Every error dh2rt raises derives from :class:`DH2Error` and is grouped by the phase in which
it arises. Each class also inherits the builtin that fits it, so callers that already catch
``ValueError``, ``OSError`` or ``RuntimeError`` keep working. Codec errors follow h11's split:
an *encode* error is ours (we asked for a frame the wire cannot carry), a *decode* error is
the other side's (bytes from a link or a file that do not decode)::

    DH2Error
    ├── ProgramError (ValueError)           a DH2 program is wrong; carries file:line:col
    │   ├── ProgramSyntaxError              the text does not parse
    │   ├── ProgramCompileError             it parses but means nothing valid
    │   └── MissingNatives                  it needs native actions this runtime lacks
    ├── UnknownName (KeyError)              the Python API was given a name the program lacks
    ├── TopologyError (ValueError)          a topology spec or file is wrong
    │   └── EventError                      an event is malformed or cannot happen
    ├── HormoneError (ValueError)           a hormone breaks a limit (too long, bad value)
    ├── ImageError (ValueError)             a serialized program image is corrupt or foreign
    │   ├── SignedImageError                a signed image is cut short or garbage (names the field and offset)
    │   └── KeyFileError                    a key file holds no Ed25519 key of the kind asked for
    ├── CodecError (ValueError)             bytes and frames do not convert
    │   ├── EncodeError                     (local) a frame this side asked for breaks a wire limit
    │   │   └── FrameEncodeError (HormoneError)  a hormone frame breaks a wire limit
    │   ├── DecodeError                     (remote) bytes from a link or a file do not decode
    │   │   ├── FrameCorrupted              a frame failed its CRC or framing
    │   │   ├── CaptureError                a capture file is not what it claims, or is cut short
    │   │   ├── TraceError                  a trace file holds a line that is no trace record
    │   │   │   └── TraceFieldError         one field is missing or of the wrong kind
    │   │   └── TrackerDatagramError        an overhead tracker's datagram is malformed (names the field)
    │   └── DxlProtocolError                Dynamixel Protocol 2.0 packets
    │       ├── DxlEncodeError (EncodeError)     values that make no valid packet
    │       └── DxlDecodeError (DecodeError)     bytes that are no valid packet
    │           └── DxlCrcError (FrameCorrupted) a packet whose CRC does not match
    ├── TransportError (OSError)            a link or bus is missing or failed
    │   └── TransportUnavailable            the interface does not exist on this machine
    ├── DriverError (RuntimeError)          a servo or its stand-in failed
    │   ├── DriverConfigError (ValueError)  a driver argument is invalid
    │   ├── ServoNotFound                   no reply from the servo id
    │   ├── ServoModelMismatch              a servo answered with the wrong model number
    │   ├── ServoCommError                  a packet was lost or garbled (CRC, timeout)
    │   ├── ServoHardwareAlert              the servo reports a hardware error
    │   ├── ServoInstructionError           the servo rejected an instruction
    │   ├── FlashError                      the module's flash holds no bootable program, or was misused
    │   ├── LatchFault                      a connector latch jammed, stalled or raised a hardware alert
    │   └── NoTrackerReading                the overhead tracker has not seen a marker, or not lately
    ├── SimulationError (RuntimeError)      the physics stand-in failed
    │   ├── PhysicsWorldError (ValueError)  a module, connector or setting of the world does not exist
    │   ├── RecordError (ValueError)        a recording parameter or sample is malformed
    │   └── GaitError (ValueError)          a gait parameter is out of range
    ├── HilError (RuntimeError)             hardware-in-the-loop tooling failed
    │   ├── MachineTooSlow                  a bare loop kept no period hil.pace may stretch to (a failure)
    │   ├── HilWorldError                   the loop's world cannot start or drive its modules
    │   ├── EmulatorError                   an emulator (servos, contacts) was misused
    │   │   └── ContactEmulatorError        a connector unknown, doubled, or touching two
    │   ├── ModuleConfigError (ValueError)  a module's configuration is malformed (names the field)
    │   └── ControlProtocolError (ValueError)  a command or report between world and module is malformed
    ├── DissectorError (RuntimeError)       the Wireshark dissector cannot be written
    │   ├── DissectorTemplateError          its Lua lost the generated block's markers
    │   └── DissectorLayoutError            the codec's layout is one it cannot describe
    └── OptionError (ValueError)            a command-line option's value cannot be used
        └── ConsoleInputError               a line typed at dh2rt console (or in its script) cannot be carried out
        ├── OutputError                     an output option names a file that cannot be written
        └── IncomparableInputs              two files a command compares cannot be compared
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


class MissingNatives(ProgramError):
    """The program declares native actions this runtime does not have."""


class UnknownName(DH2Error, KeyError):
    """A variable, sensor or receptor name given to the Python API is not in the program."""

    def __str__(self) -> str:  # KeyError would show the message in quotes
        return str(self.args[0]) if self.args else ""


class TopologyError(DH2Error, ValueError):
    """A topology spec or file is wrong."""


class EventError(TopologyError):
    """An event string is malformed, names an unknown module, connector or hormone, or cannot
    happen on the robot's links at its cycle."""


class HormoneError(DH2Error, ValueError):
    """A hormone breaks a limit (content too long, value out of range)."""


class ImageError(DH2Error, ValueError):
    """A serialized program image is corrupt, truncated or of another format version."""


class SignedImageError(ImageError):
    """A signed image is cut short or its fields are garbage; the message names the field
    and its offset."""


class KeyFileError(ImageError):
    """A key file holds no Ed25519 key of the kind asked for (private or public)."""


class CodecError(DH2Error, ValueError):
    """Bytes and frames do not convert (see EncodeError and DecodeError)."""


class EncodeError(CodecError):
    """Local: this side asked for a frame the wire cannot carry (a bug or a limit here)."""


class FrameEncodeError(EncodeError, HormoneError):
    """A frame cannot be encoded: a connector, sequence number or digest breaks a wire limit."""


class DecodeError(CodecError):
    """Remote: bytes received on a link (or read from a file) do not decode."""


class FrameCorrupted(DecodeError):
    """A frame failed its CRC or its framing."""


class CaptureError(DecodeError):
    """A capture file is not what it claims, or is cut short; the message names the file and
    the offset or record."""


class TraceError(DecodeError):
    """A trace file that cannot be read or holds a line that is not a trace record (the
    message names the file, the line and the column or field)."""


class TraceFieldError(TraceError):
    """A trace record's ``field`` is missing (``expected`` None) or holds ``value`` where
    ``expected`` (a description) belongs; the reader adds the file and line."""

    def __init__(self, field: str, expected: str | None = None, value: object = None) -> None:
        super().__init__(f"field {field}: " + ("missing" if expected is None else f"expected {expected}"))
        self.field, self.expected, self.value = field, expected, value


class TrackerDatagramError(DecodeError):
    """A datagram from the overhead tracker (:mod:`dh2rt.wire.tracker`) is malformed: ``field``
    names what is wrong and ``offset`` the byte it starts at."""

    def __init__(self, field: str, offset: int, message: str) -> None:
        super().__init__(f"tracker datagram, {field} (byte {offset}): {message}")
        self.field, self.offset = field, offset


class DxlProtocolError(CodecError):
    """Bytes or values that do not make a valid Dynamixel Protocol 2.0 packet."""


class DxlEncodeError(DxlProtocolError, EncodeError):
    """Local: values that make no valid Protocol 2.0 packet (an id, a length out of range)."""


class DxlDecodeError(DxlProtocolError, DecodeError):
    """Remote: bytes that are no valid Protocol 2.0 packet."""


class DxlCrcError(DxlDecodeError, FrameCorrupted):
    """A framed Dynamixel packet whose CRC does not match."""


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


class DriverConfigError(DriverError, ValueError):
    """A driver argument is invalid (the message names it)."""


class ServoInstructionError(DriverError):
    """The servo answered but rejected the instruction (access, data range or limit error)."""


class FlashError(DriverError):
    """The module's flash directory holds no program it may boot (nothing confirmed, or the
    confirmed image fails its checks), or was asked for a step its state does not allow."""


class LatchFault(DriverError):
    """A connector latch (:mod:`drivers.latch`) is at fault until its next command: jammed,
    stalled, or its servo raised a hardware alert."""


class NoTrackerReading(DriverError):
    """The overhead tracker has reported no pose of ``marker`` (module ``module``), ever
    (``age_s`` None) or within the bound the caller asked for (``age_s`` the latest one's age).
    A module must not steer by a pose it does not have: this is never a silent zero."""

    def __init__(self, marker: int, module: str, age_s: float | None, max_age_s: float) -> None:
        when = "never seen" if age_s is None else f"last seen {age_s:.3f} s ago (bound {max_age_s:g} s)"
        super().__init__(f"no tracker reading of marker {marker} ({module}): {when}")
        self.marker, self.module, self.age_s, self.max_age_s = marker, module, age_s, max_age_s


class PhysicsWorldError(SimulationError, ValueError):
    """A physics World was asked about a module, connector or setting that does not exist."""


class RecordError(SimulationError, ValueError):
    """A recording parameter or sample is malformed."""


class GaitError(SimulationError, ValueError):
    """A gait parameter is out of range."""


class HilError(DH2Error, RuntimeError):
    """Hardware-in-the-loop tooling failed."""


class MachineTooSlow(HilError):
    """Even a bare sleep loop kept no loop period hil.pace may stretch to: the test that met it
    fails, saying what the bare loop measured (no test is skipped for a slow machine)."""


class HilWorldError(HilError):
    """The loop's world cannot start or drive its modules."""


class EmulatorError(HilError):
    """An emulator was misused: the servo emulator (bad id, restarted after stop, unknown
    fault) or the contact emulator."""


class ContactEmulatorError(EmulatorError):
    """The contact emulator was misused: an unknown or duplicate connector, a connector asked to
    touch a second one, a contact broken that was not made."""


class ModuleConfigError(HilError, ValueError):
    """A module's configuration is malformed; the message names the field."""


class ControlProtocolError(HilError, ValueError):
    """A command or report between the world and a module is malformed; names the field."""


class DissectorError(DH2Error, RuntimeError):
    """The Wireshark dissector cannot be written (``dh2rt wireshark``)."""


class DissectorTemplateError(DissectorError):
    """The dissector's Lua has lost its generated block's markers."""


class DissectorLayoutError(DissectorError):
    """The codec's layout is one the dissector cannot describe."""


class OptionError(DH2Error, ValueError):
    """A command-line option has a value the command cannot use (exit 2)."""


class ConsoleInputError(OptionError):
    """A line typed at ``dh2rt console`` (or read from its script) names a hormone, a path or
    a command it cannot carry out (said at the prompt; exit 2 in a script)."""


class OutputError(OptionError):
    """An output option names a file that cannot be written as asked (exit 2)."""


class IncomparableInputs(OptionError):
    """Two files a command compares cannot be compared (not traces, different robots)."""
