"""ELMO drives over CANopen (CiA 301 / CiA 402): codec, transport, SDO, device, emulator."""
