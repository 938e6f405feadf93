"""Where a batch is decoded: bytes to a validated ``SensorBatch``, a batch to the engine's arrays."""
