"""The link model between robots: range, seeded loss, latency and bandwidth; what one robot
offers its links (new updates, re-sends, gap requests); the relay's bookkeeping."""
