"""The Lua scripts that make each change of a dataset record (seasynth.service.records.store) and of the queue side's
coordination (seasynth.service.records.coordination) atomic in Redis."""

# Counts an execution unless the shard has used up its attempts (then returns -1 and counts nothing), or the
# record is gone (-2: Redis lost it; nothing is written, so no partial record appears).
START = """
if redis.call('EXISTS', KEYS[1]) == 0 then return -2 end
local tries = tonumber(redis.call('HGET', KEYS[2], ARGV[1]) or '0')
if tries >= tonumber(ARGV[4]) then return -1 end
tries = redis.call('HINCRBY', KEYS[2], ARGV[1], 1)
redis.call('HINCRBY', KEYS[1], 'attempts', 1)
redis.call('HSETNX', KEYS[1], 'started_at', ARGV[2])
redis.call('HSET', KEYS[1], 'touched_at', ARGV[2])
if redis.call('HGET', KEYS[1], 'state') == 'queued' then redis.call('HSET', KEYS[1], 'state', 'running') end
redis.call('HSET', KEYS[3], ARGV[1], ARGV[3])
return tries
"""

# SADD first: only the first commit of a shard adds its frames, however many times it runs. A record Redis lost
# is not recreated in part: the commit marker in the bucket is adopted when the record is restored. A shard given
# up as failed whose marker turns up after all (its last attempt wrote it, then died) is committed: it leaves the
# failed set (KEYS[4]), its error and the shown failed indices (KEYS[5], KEYS[6]), so it is never counted twice.
# ARGV[4]: the new touched_at, or '' to leave it (a restore, which wants the dataset swept at once).
COMMIT = """
if redis.call('EXISTS', KEYS[1]) == 0 then return {0, 0, 0} end
local added = redis.call('SADD', KEYS[2], ARGV[1])
if added == 1 then
  redis.call('HINCRBY', KEYS[1], 'frames_done', ARGV[2])
  redis.call('HSET', KEYS[3], ARGV[1], ARGV[3])
  if ARGV[4] ~= '' then redis.call('HSET', KEYS[1], 'touched_at', ARGV[4]) end
  if redis.call('SREM', KEYS[4], ARGV[1]) == 1 then
    redis.call('HDEL', KEYS[5], ARGV[1])
    redis.call('ZREM', KEYS[6], ARGV[1])
  end
end
return {added, redis.call('SCARD', KEYS[2]), redis.call('SCARD', KEYS[4])}
"""

# A newly failed shard also joins the ERRORS_SHOWN (ARGV[4]) lowest failed indices, if it is one of them.
FAIL = """
if redis.call('EXISTS', KEYS[1]) == 0 then return {0, 0, 0} end
redis.call('HSET', KEYS[3], ARGV[1], ARGV[2])
local added = 0
if redis.call('SISMEMBER', KEYS[4], ARGV[1]) == 0 then added = redis.call('SADD', KEYS[2], ARGV[1]) end
if added == 1 then
  redis.call('HSET', KEYS[1], 'touched_at', ARGV[3])
  redis.call('ZADD', KEYS[5], ARGV[1], ARGV[1])
  redis.call('ZREMRANGEBYRANK', KEYS[5], tonumber(ARGV[4]), -1)
end
return {added, redis.call('SCARD', KEYS[4]), redis.call('SCARD', KEYS[2])}
"""

# {index, error, ...} of the shown failed shards (KEYS: failed, shown, errors; ARGV[1]: ERRORS_SHOWN), in index
# order. Fewer shown than failed, with room for more, only happens to a record written before failed shards were
# indexed: they are indexed then, once.
ERRORS = """
local limit = tonumber(ARGV[1])
local shown = redis.call('ZCARD', KEYS[2])
if shown < limit and shown < redis.call('SCARD', KEYS[1]) then
  for _, i in ipairs(redis.call('SMEMBERS', KEYS[1])) do redis.call('ZADD', KEYS[2], i, i) end
  redis.call('ZREMRANGEBYRANK', KEYS[2], limit, -1)
end
local out = {}
for _, i in ipairs(redis.call('ZRANGE', KEYS[2], 0, -1)) do
  out[#out + 1] = i
  out[#out + 1] = redis.call('HGET', KEYS[3], i) or ''
end
return out
"""

# Moves a live dataset to a terminal state; a terminal one keeps its state. Returns the state after.
FINISH = """
local s = redis.call('HGET', KEYS[1], 'state')
if not s then return nil end
if s == 'queued' or s == 'running' then
  redis.call('HSET', KEYS[1], 'state', ARGV[1], 'finished_at', ARGV[2])
  return ARGV[1]
end
return s
"""

# Sets fields of an existing record only: a late writer never recreates a discarded dataset's hash.
UPDATE = """
if redis.call('EXISTS', KEYS[1]) == 0 then return 0 end
redis.call('HSET', KEYS[1], unpack(ARGV))
return 1
"""

# Recreates a record Redis lost, unless one exists (two restorers race: one wins). ARGV: score, id, fields...
RESTORE = """
if redis.call('EXISTS', KEYS[1]) == 1 then return 0 end
redis.call('HSET', KEYS[1], unpack(ARGV, 3))
redis.call('ZADD', KEYS[2], ARGV[1], ARGV[2])
return 1
"""

# Decides a complete dataset's final state in one step, unless it is final already (a cancel came first): the
# state, finished_at, and the dataset's entry in the set of manifests still to write (KEYS[2]). Returns the state
# after.
DECIDE = """
local s = redis.call('HGET', KEYS[1], 'state')
if not s then return nil end
if s == 'queued' or s == 'running' then
  redis.call('HSET', KEYS[1], 'state', ARGV[1], 'finished_at', ARGV[2])
  redis.call('SADD', KEYS[2], ARGV[3])
  return ARGV[1]
end
return s
"""

# Counts a hand-back of a shard to a worker of the pinned renderer and keeps the dataset from looking stalled (a
# sweep would publish the shard again while its message goes round); KEYS[2]: the dataset's handed-back shards.
# waiting_since: the first hand-back since a live worker of the pinned renderer was last seen (ARGV[3] == '1': one
# is live now). Returns {hand-backs, waiting_since or ''}, nil for no such dataset.
HAND_BACK = """
if redis.call('EXISTS', KEYS[1]) == 0 then return nil end
local n = redis.call('HINCRBY', KEYS[1], 'handbacks', 1)
redis.call('HSET', KEYS[1], 'touched_at', ARGV[2])
redis.call('HSET', KEYS[2], ARGV[1], ARGV[2])
if ARGV[3] == '1' then
  redis.call('HDEL', KEYS[1], 'waiting_since')
  return {n, ''}
end
redis.call('HSETNX', KEYS[1], 'waiting_since', ARGV[2])
return {n, redis.call('HGET', KEYS[1], 'waiting_since')}
"""

# A worker of the pinned renderer took a shard: nothing is waiting for one any more.
FOUND = """
redis.call('HDEL', KEYS[2], ARGV[1])
if redis.call('HEXISTS', KEYS[1], 'notice') == 1 then redis.call('HDEL', KEYS[1], 'notice', 'waiting_since') end
return 0
"""
