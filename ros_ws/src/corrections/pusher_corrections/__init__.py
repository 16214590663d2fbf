"""The corrections stage of HIL-SERL.

The mux (policy vs. human arbitration) and the corrector (a scripted stand-in for the
person, or a keyboard for a real one).
"""
