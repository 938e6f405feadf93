"""Pure numerics of crowdslam: arrays in, arrays out. No I/O, no pydantic, no SQL, no asyncio, no clock."""
