"""The dataset spec: the pydantic models a spec file or a POST /datasets body is read into (dataset.py is the
whole spec; scene.py, light.py, outputs.py and sensors.py its sections; types.py the shared field types)."""
