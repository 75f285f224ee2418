"""Pure measurement functions that measurement models name by dotted path.

Each takes one decoded sample (a mapping, as it arrives from the bus) of a port's data type and
returns a Context Dependent Measurement value (paper Sec. III-C). No I/O, no state.
"""
