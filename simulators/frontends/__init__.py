"""Controller-side protocol front-ends of the simulated CNC (serial DNC, OPC UA, Modbus, CAN)."""
