"""A simulated CNC control and the servers that reach it: the seed protocol over TCP.

`control` is the machine (program store, modes, DNC window, running line); each server
module speaks one link to it. Imports only `worker.transports` of ours.
"""
