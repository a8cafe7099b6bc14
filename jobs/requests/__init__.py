"""Requests a machine sends: recognised in a received program, planned, answered (pure).

`recognise` finds the commands, `plan` turns them into steps, `answers` writes the programs
sent back, `explain` says what a text would trigger. Nothing here does I/O.
"""
