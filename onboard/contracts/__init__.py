"""The contracts between layers (thesis Def. 3.4-3.7, lines 1441-1460; ch. 8.1).

What one layer promises another, and nothing else: the message schemas and binary layouts,
the one topic table, the one place for parameters and limits, the commander rule (who may
drive the motors), the tracking tube the low level measures and the planner tightens by, and
how a CoM reference is read at a time. Assumes nothing below it; every layer above reads it.
"""
