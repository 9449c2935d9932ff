"""The streaming engine behind `integrate`: blocks over chunks and devices, their static
sizes, tolerances, and VEGAS+ rounds."""
