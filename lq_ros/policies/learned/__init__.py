"""The learned chunk policies' inference side: networks, the observation features, and checkpoint loading."""
