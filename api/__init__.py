"""seasynth's HTTP adapter: routes, dependencies, auth and error mapping. It enqueues by task name and never
imports worker code, so the API image needs no OpenGL."""
