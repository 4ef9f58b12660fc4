"""flightstack: distributed-GP cooperative visual pursuit for drone networks."""
