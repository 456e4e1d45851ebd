"""MAVLink: the link to the autopilot, and PX4's conventions (NED/FRD, boot time, custom modes).

Nothing outside this package sees NED, FRD or PX4's mode numbers; see DESIGN.md.
"""
