/*
 * sigsafe.c - bounded text and whole writes, safe in a signal handler
 * (sigsafe.h).
 */
#include "sigsafe.h"

#include <errno.h>
#include <unistd.h>

void ss_mem(struct ss_buf *o, const char *s, size_t n)
{
    for (size_t i = 0; i < n && o->n < o->cap; i++)
        o->b[o->n++] = s[i];
}

void ss_str(struct ss_buf *o, const char *s)
{
    while (s && *s && o->n < o->cap)
        o->b[o->n++] = *s++;
}

static void put_unsigned(struct ss_buf *o, unsigned long v, unsigned base)
{
    char digits[24];
    int i = 0;
    do
        digits[i++] = "0123456789abcdef"[v % base];
    while ((v /= base) && i < (int)sizeof digits);
    while (i && o->n < o->cap)
        o->b[o->n++] = digits[--i];
}

void ss_dec(struct ss_buf *o, long v)
{
    if (v < 0) {
        ss_str(o, "-");
        put_unsigned(o, -(unsigned long)v, 10);
    } else {
        put_unsigned(o, (unsigned long)v, 10);
    }
}

void ss_hex(struct ss_buf *o, unsigned long v)
{
    ss_str(o, "0x");
    put_unsigned(o, v, 16);
}

void ss_ratio(struct ss_buf *o, uint64_t num, uint64_t den, int decimals)
{
    uint64_t scale = 1;
    for (int i = 0; i < decimals; i++)
        scale *= 10;
    unsigned __int128 scaled = (unsigned __int128)num * scale;
    uint64_t q = (uint64_t)(scaled / den), r = (uint64_t)(scaled % den);
    if (r > den - r || (r == den - r && (q & 1)))
        q++;
    put_unsigned(o, q / scale, 10);
    if (decimals > 0) {
        ss_str(o, ".");
        for (uint64_t d = scale / 10, f = q % scale; d > 0; d /= 10)
            ss_mem(o, &"0123456789"[f / d % 10], 1);
    }
}

char *ss_cstr(struct ss_buf *o)
{
    o->b[o->n] = '\0';
    return o->b;
}

int ss_write_all(int fd, const char *s, size_t n)
{
    while (n > 0) {
        ssize_t w = write(fd, s, n);
        if (w < 0 && errno == EINTR)
            continue;
        if (w <= 0)
            return -1;
        s += w;
        n -= (size_t)w;
    }
    return 0;
}

void ss_flush(struct ss_buf *o, int fd)
{
    ss_write_all(fd, o->b, o->n);
    o->n = 0;
}
