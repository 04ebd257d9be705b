"""ARCHER's own flywheel-board firmware over UDP: codec, transport, device, emulator."""
