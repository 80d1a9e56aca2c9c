"""Bits of the per-frame ``flags`` of the rendering loop, in one table.

The display sets the low bits in its Encoder frames (docs/protocol.md); the host's
controller sets the high bits; play logs store both ORed together.
"""

FLAG_WATCHDOG = 0x01  # display: V zeroed because SetVoltage frames stopped arriving
FLAG_LIMIT = 0x02  # display: the piston is pressed against an end stop
# display: the voltage in use is not the host's answer to the frame before this one
# (the answer had not arrived: the host or the line was late; docs/protocol.md, 7)
FLAG_STALE = 0x04
# display: the answer to the frame before was late, and the voltage in use comes from
# the local model of the last answer (SetModel), at most its horizon periods old
FLAG_MODEL = 0x08
SATURATED = 0x10  # controller: the law asked for more than v_max; V = v_max
UNRENDERABLE = 0x20  # controller: the law asked the solenoid to push; V = 0
NONFINITE = 0x40  # controller: an input or the law was NaN or infinite; V = 0
