# cosim5g/prometheus: Debian's prometheus package on the cosim5g base (no registry needed).
# The configuration is bind-mounted from configs/prometheus/ by docker-compose.yml.
ARG BASE_IMAGE=cosim5g/base:bookworm
FROM ${BASE_IMAGE}
LABEL org.opencontainers.image.title="cosim5g prometheus" \
      org.opencontainers.image.vendor="cosim5g" \
      cosim5g.image="prometheus"
ENV DEBIAN_FRONTEND=noninteractive
# --no-install-recommends keeps the node exporter out. wget: the compose healthcheck
# (GET /-/ready); the package makes the unprivileged `prometheus` user. The dpkg filter drops
# docs, man pages, translations and moment-timezone's historic tz data (214 MB of JSON the web
# UI never loads: it uses the prebuilt moment-timezone-with-data bundle).
RUN printf '%s\n' 'path-exclude=/usr/share/doc/*' 'path-include=/usr/share/doc/*/copyright' \
      'path-exclude=/usr/share/man/*' 'path-exclude=/usr/share/locale/*' \
      'path-exclude=/usr/share/javascript/moment-timezone/data/*' \
      >/etc/dpkg/dpkg.cfg.d/cosim5g-slim \
 && apt-get update \
 && apt-get install -y --no-install-recommends prometheus wget ca-certificates \
 && rm -rf /var/lib/apt/lists/* /var/cache/apt/archives/*.deb \
 && install -d -o prometheus -g prometheus /prometheus
# docker-compose.yml runs Prometheus as the owner of the coordinator's API token file (mode 0600),
# any uid: the data folder (a fresh volume copies these permissions) takes whoever runs it.
RUN chmod 1777 /prometheus
USER prometheus
WORKDIR /prometheus
EXPOSE 9090
ENTRYPOINT ["/usr/bin/prometheus"]
CMD ["--config.file=/etc/prometheus/prometheus.yml", "--storage.tsdb.path=/prometheus", \
     "--web.listen-address=:9090"]
