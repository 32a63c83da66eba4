"""Shipped ELO scenes (XML, millimetres). Installed as ``elo_mitsuba.scenes``."""
