"""One APIRouter module per resource: ops (health, metrics), rig, measurements, schedules."""
