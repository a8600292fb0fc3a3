"""Running tasks: claiming, heartbeats, the view batch, computing and recording results."""
