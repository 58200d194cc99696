"""CiA 309 access to the card's CANopen networks (docs/cia309.md).

Import-light on purpose: the typed service layer, the 309-3 ASCII codec
(:mod:`host_api.cia309.ascii`) and its data type codecs
(:mod:`host_api.cia309.datatypes`) are separate modules, so a program that needs one
does not pay for the others.
"""
