/* bell.c - the doorbell [ours] (see bell.h) and the SHA-1 that names the device's socket. */
#ifndef _GNU_SOURCE
#define _GNU_SOURCE
#endif
#include "bell.h"

#include <errno.h>
#include <limits.h>
#include <poll.h>
#include <stddef.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#define RING_WANT_ACK 0x02

static uint32_t rol(uint32_t v, int n) { return (v << n) | (v >> (32 - n)); }

static void sha1_block(uint32_t h[5], const unsigned char *p) {
  uint32_t w[80], a, b, c, d, e, f, k, t;
  int i;
  for (i = 0; i < 16; i++)
    w[i] = (uint32_t)p[4 * i] << 24 | (uint32_t)p[4 * i + 1] << 16 | (uint32_t)p[4 * i + 2] << 8 |
           (uint32_t)p[4 * i + 3];
  for (i = 16; i < 80; i++) w[i] = rol(w[i - 3] ^ w[i - 8] ^ w[i - 14] ^ w[i - 16], 1);
  a = h[0]; b = h[1]; c = h[2]; d = h[3]; e = h[4];
  for (i = 0; i < 80; i++) {
    if (i < 20) { f = (b & c) | (~b & d); k = 0x5A827999u; }
    else if (i < 40) { f = b ^ c ^ d; k = 0x6ED9EBA1u; }
    else if (i < 60) { f = (b & c) | (b & d) | (c & d); k = 0x8F1BBCDCu; }
    else { f = b ^ c ^ d; k = 0xCA62C1D6u; }
    t = rol(a, 5) + f + e + k + w[i];
    e = d; d = c; c = rol(b, 30); b = a; a = t;
  }
  h[0] += a; h[1] += b; h[2] += c; h[3] += d; h[4] += e;
}

void cifemu_sha1(const unsigned char *data, size_t length, unsigned char digest[20]) {
  uint32_t h[5] = {0x67452301u, 0xEFCDAB89u, 0x98BADCFEu, 0x10325476u, 0xC3D2E1F0u};
  unsigned char tail[128];
  size_t full = length / 64 * 64, rest = length - full, tail_len;
  uint64_t bits = (uint64_t)length * 8;
  size_t i;
  for (i = 0; i < full; i += 64) sha1_block(h, data + i);
  memset(tail, 0, sizeof tail);
  memcpy(tail, data + full, rest);
  tail[rest] = 0x80;
  tail_len = rest + 1 + 8 <= 64 ? 64 : 128;
  for (i = 0; i < 8; i++) tail[tail_len - 1 - i] = (unsigned char)(bits >> (8 * i));
  sha1_block(h, tail);
  if (tail_len == 128) sha1_block(h, tail + 64);
  for (i = 0; i < 20; i++) digest[i] = (unsigned char)(h[i / 4] >> (24 - 8 * (i % 4)));
}

int cifemu_bell_open(cifemu_bell *bell, const char *image_path) {
  static const char hex[] = "0123456789abcdef";
  static const char prefix[] = "cifemu-dpm-";
  char resolved[PATH_MAX];
  unsigned char digest[20];
  struct sockaddr_un self;
  size_t n = sizeof prefix - 1;
  int i;

  memset(bell, 0, sizeof *bell);
  bell->device_wants_ack = 1; /* nothing waits on a missed hint */
  if (realpath(image_path, resolved) == NULL) return -1;
  cifemu_sha1((const unsigned char *)resolved, strlen(resolved), digest);
  bell->device.sun_family = AF_UNIX;
  bell->device.sun_path[0] = '\0';
  memcpy(bell->device.sun_path + 1, prefix, n);
  for (i = 0; i < 10; i++) {
    bell->device.sun_path[1 + n + 2 * i] = hex[digest[i] >> 4];
    bell->device.sun_path[2 + n + 2 * i] = hex[digest[i] & 15];
  }
  bell->device_len = (socklen_t)(offsetof(struct sockaddr_un, sun_path) + 1 + n + 20);
  bell->fd = socket(AF_UNIX, SOCK_DGRAM | SOCK_NONBLOCK | SOCK_CLOEXEC, 0);
  if (bell->fd < 0) return -1;
  memset(&self, 0, sizeof self);
  self.sun_family = AF_UNIX;
  if (bind(bell->fd, (struct sockaddr *)&self, sizeof(sa_family_t)) != 0) { /* autobind */
    close(bell->fd);
    bell->fd = -1;
    return -1;
  }
  return 0;
}

void cifemu_bell_close(cifemu_bell *bell) {
  if (bell->fd >= 0) close(bell->fd);
  bell->fd = -1;
}

void cifemu_bell_ring(cifemu_bell *bell) {
  static const unsigned char ring = 0x01;
  /* A refused or full queue costs the device one poll interval, never correctness. */
  (void)sendto(bell->fd, &ring, 1, MSG_DONTWAIT | MSG_NOSIGNAL,
               (const struct sockaddr *)&bell->device, bell->device_len);
}

int cifemu_bell_wait(cifemu_bell *bell, long long timeout_ns) {
  struct pollfd pfd;
  unsigned char buf[16];
  int rung = 0;
  ssize_t got;
  pfd.fd = bell->fd;
  pfd.events = POLLIN;
  if (timeout_ns < 0) timeout_ns = 0;
  /* whole milliseconds, rounded up: a wait never ends before its time */
  if (poll(&pfd, 1, (int)((timeout_ns + 999999) / 1000000)) <= 0) return 0;
  while ((got = recv(bell->fd, buf, sizeof buf, MSG_DONTWAIT)) > 0) {
    rung = 1;
    __atomic_store_n(&bell->device_wants_ack, buf[0] == RING_WANT_ACK, __ATOMIC_RELAXED);
  }
  return rung;
}
