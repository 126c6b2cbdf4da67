"""The ground floor: errors, limits, plug-ins, threads and file safety that every other package may use."""
