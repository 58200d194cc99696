"""CiA 309 access to the card's CANopen networks (docs/cia309.md).

Import-light on purpose: the typed service layer (:mod:`host_api.cia309.gateway` over
:mod:`host_api.cia309.model`) and the 309-3 text layer (framing, parser, formatters, value
texts) are separate modules, and the typed layer never imports the text layer, so a program
that needs one does not pay for the other.
"""
