"""Teensy microcontroller over a framed serial link: protocol, transport, device, emulator."""
