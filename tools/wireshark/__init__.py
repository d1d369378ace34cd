"""Wireshark support for dh2rt captures: a Lua dissector (``dh2rt.lua``) for dh2rt frames on
SocketCAN and on the emulated serial links, and the generator that writes it from the codec's
layout and a program's vocabulary (``dh2rt wireshark``, :mod:`.command`)."""
