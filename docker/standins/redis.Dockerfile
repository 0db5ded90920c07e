# Stand-in for the official redis image (docker/standins/build.sh tags it as docker-compose.yml's redis:<tag>):
# Debian's redis-server on the stand-in python base, run as the image's entrypoint runs it.
ARG BASE=python:3.11-slim
FROM ${BASE}
# No service starts during the build (the package's postinst would start one).
RUN printf '#!/bin/sh\nexit 101\n' > /usr/sbin/policy-rc.d && chmod +x /usr/sbin/policy-rc.d \
 && apt-get update \
 && apt-get install -y --no-install-recommends redis-server redis-tools \
 && rm -rf /var/lib/apt/lists/* /usr/sbin/policy-rc.d \
 && mkdir -p /data && chown redis:redis /data
COPY docker/standins/redis-entrypoint.sh /usr/local/bin/docker-entrypoint.sh
VOLUME /data
WORKDIR /data
# The official image starts as root and drops to redis; this one is redis from the start (a new volume copies
# /data's ownership).
USER redis
ENTRYPOINT ["docker-entrypoint.sh"]
EXPOSE 6379
CMD ["redis-server"]
