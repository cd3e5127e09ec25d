"""The simulation: the batched simulator (`env`), terrain, a gymnasium adapter, and a toy for the learning tests."""
